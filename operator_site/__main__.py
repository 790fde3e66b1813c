from operator_site.cli import run

run()
