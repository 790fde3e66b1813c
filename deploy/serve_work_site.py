"""``work-site serve`` for deployment tests: the same server and options, with TLS, access
control and link lease (``--certs``, ``--operators``, ``--lease-ms``, now options of
``work-site serve`` itself)::

    python deploy/serve_work_site.py --listen tls/0.0.0.0:7447 --certs certs/ \\
        --operators operator --lease-ms 3000

The one difference: without ``--journal`` the programs received are remembered in a fresh
temporary file, i.e. for this process only (tests reuse program ids from run to run).
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:  # run as a script from anywhere
    sys.path.insert(0, str(REPO))

from work_site.cli import main as work_site_main  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    """Serve until SIGINT/SIGTERM; the exit code of ``work-site serve``."""
    argv = list(sys.argv[1:] if argv is None else argv)
    with tempfile.TemporaryDirectory(prefix="serve_work_site-") as tmp:
        if not any(a == "--journal" or a.startswith("--journal=") for a in argv):
            argv += ["--journal", str(Path(tmp) / "programs.jsonl")]
        return work_site_main(["serve", *argv])


if __name__ == "__main__":
    sys.exit(main())
