"""The benchmarks: each measures part of the product and writes its figures.

Run from the repository root as ``python -m bench NAME [options]`` (``python -m bench --help``
lists them). A benchmark prints its JSON summary as its last line and writes CSV and PNG files
into ``--out``; ``python -m bench report`` rebuilds the summary of docs/benchmarks.md from the
JSON. Not part of the wheel: the product never imports this package.
"""
