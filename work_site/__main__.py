from work_site.cli import run

run()
