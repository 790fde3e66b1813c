"""A fleet on one machine: zenoh routers, N work sites and operator pages, all on loopback.

    python deploy/fleet.py --sites 3 [--routers 2] [--site-routers] [--pages 1] [--tls DIR]
        [--port 7600] [--logs DIR]

Starts ``deploy/router.py`` on ``--port`` (commands) and the next port (state, camera), and with
``--routers 2`` a second router on the two ports after, meshed with the first (the shared
routers: a cloud router and its stand-in); then N ``work-site serve`` processes with site ids
``cell-01`` … ``cell-NN``, each listening on a loopback port of its own and connected to every
shared router, and ``--pages`` operator pages (``operator-site serve``, ports 8080, 8081, …),
page k for cell k, as zenoh clients of the shared routers (through the first, the next if it
fails): everything they send and receive goes through a router. With ``--site-routers`` each
work site is instead behind a router of its own (``router-cell-NN``, the next ports), meshed with
the shared ones: a router per site and a cloud router, as cells in several buildings would run.
Prints each router, site and page, then runs until Ctrl-C and stops everything. Each process
logs to ``--logs`` (default: a temporary directory, printed).

``--tls DIR``: mutual TLS with per-cell identities and the router's access control: DIR holds
``deploy/make-certs.sh`` certificates (made if DIR has no ``ca.pem``) with, per cell, a work site
``cell-NN-work-site`` and an operator ``cell-NN-operator``; each router is given one ``--cell``
per site it serves, so an operator's certificate commands and sees its own cell only.

From Python (``bench fleet``, the tests): ``with Fleet(FleetSpec(sites=3), log_dir) as fleet:``
then ``fleet.operator_config(site_id)`` for a zenoh session that reaches a cell as its operator.
"""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:  # run as a script from anywhere
    sys.path.insert(0, str(REPO))

import zenoh  # noqa: E402

from protocol.session import TlsFiles, free_port_pair, link_endpoints, make_config  # noqa: E402

MAX_ROUTERS = 2
"""Routers one fleet meshes (the first, and one to fail over to)."""
MAX_SITES = 40
"""Sites one fleet starts: each is a simulator with a camera, so a handful fill a small machine;
past this the ports and the router's access list grow without a machine to run them."""
UP_TIMEOUT_S = 120.0
"""A process that has not said it is up this long after its start is taken as failed (s): a
work site loads its scene, models and renderer, and N of them start on a few cores at once."""
STOP_TIMEOUT_S = 15.0
"""A process still running this long after SIGTERM is killed (s)."""


def site_id(index: int) -> str:
    """The site id of the fleet's cell ``index`` (0-based): ``cell-01``, ``cell-02``, …"""
    return f"cell-{index + 1:02d}"


def work_site_cn(site: str) -> str:
    """The common name of ``site``'s work-site certificate."""
    return f"{site}-work-site"


def operator_cn(site: str) -> str:
    """The common name of ``site``'s operator certificate."""
    return f"{site}-operator"


@dataclass(frozen=True)
class FleetSpec:
    """What a :class:`Fleet` starts."""

    sites: int
    routers: int = 1
    """Shared routers, meshed (the operators' routers: a cloud router, and one to fail over
    to)."""
    site_routers: bool = False
    """Each work site behind a router of its own (its site's), meshed with the shared routers:
    the work site connects to its site router only, operators to the shared ones."""
    pages: int = 0
    """Operator pages, page k for cell k (at most one per site)."""
    tls: Path | None = None
    """Certificates for mutual TLS and per-cell access control (None: plain loopback)."""
    port: int = 0
    """The first router's command port (its state and camera port is the next); a second router, the
    site routers and then the work sites' listeners take the pairs after (0: free pairs)."""
    page_port: int = 8080
    camera: bool = True
    vision_rate_hz: float = 0.0
    """The work sites' recognition rate (0: off; vision at start-up takes the cores for
    seconds per site)."""
    site_args: tuple[str, ...] = ()
    """More ``work-site serve`` options, for every site."""

    def __post_init__(self) -> None:
        if not 1 <= self.sites <= MAX_SITES:
            raise ValueError(f"sites = {self.sites}: must be 1..{MAX_SITES}")
        if not 1 <= self.routers <= MAX_ROUTERS:
            raise ValueError(f"routers = {self.routers}: must be 1..{MAX_ROUTERS}")
        if not 0 <= self.pages <= self.sites:
            raise ValueError(f"pages = {self.pages}: must be 0..sites ({self.sites})")
        pairs = self.routers + self.sites * (2 if self.site_routers else 1)
        top = 65536 - 2 * pairs
        if self.port and not 1024 <= self.port <= top:
            raise ValueError(f"port = {self.port}: must be 1024..{top} (or 0: free pairs)")

    @property
    def site_ids(self) -> list[str]:
        return [site_id(k) for k in range(self.sites)]


@dataclass(frozen=True)
class RouterPlan:
    """One router of a fleet: where it listens, the routers it meshes with (their endpoints),
    the cells it admits, and the site it is the router of (None: a shared router)."""

    endpoint: str
    mesh: tuple[str, ...]
    sites: tuple[str, ...]
    site: str | None = None


@dataclass
class Fleet:
    """The routers, work sites and pages of ``spec``, each a process logging into ``log_dir``;
    a context manager that stops them all (also after an error while starting)."""

    spec: FleetSpec
    log_dir: Path
    routers: dict[str, RouterPlan] = field(default_factory=dict)
    """Each router by process name: ``router``, ``router-2`` (shared), ``router-cell-01`` …"""
    procs: dict[str, subprocess.Popen] = field(default_factory=dict)
    pages: dict[str, str] = field(default_factory=dict)
    """Each page's site id → its address."""

    def __enter__(self) -> Fleet:
        try:
            self.start()
        except BaseException:
            self.stop()
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def log(self, name: str) -> Path:
        return self.log_dir / f"{name}.log"

    def _spawn(self, name: str, argv: list[str]) -> subprocess.Popen:
        if self.log(name).exists():  # started again: the earlier run's log is kept aside
            runs = len(list(self.log_dir.glob(f"{name}.*.log")))
            self.log(name).rename(self.log_dir / f"{name}.{runs + 1}.log")
        with self.log(name).open("w") as log:
            proc = subprocess.Popen(
                argv, cwd=REPO, stdout=log, stderr=subprocess.STDOUT, start_new_session=True,
                env={**os.environ, "PYTHONUNBUFFERED": "1"},
            )  # fmt: skip
        self.procs[name] = proc
        return proc

    def _wait_for(self, name: str, text: str) -> None:
        deadline = time.monotonic() + UP_TIMEOUT_S
        while text not in self.log(name).read_text(errors="replace"):
            if self.procs[name].poll() is not None:
                raise RuntimeError(f"{name} ended while starting:\n{self.tail(name)}")
            if time.monotonic() > deadline:
                raise TimeoutError(f"{name} not up in {UP_TIMEOUT_S:.0f} s:\n{self.tail(name)}")
            time.sleep(0.1)

    def tail(self, name: str, lines: int = 20) -> str:
        """The last lines of process ``name``'s log."""
        return "\n".join(self.log(name).read_text(errors="replace").splitlines()[-lines:])

    def _certs(self, name: str) -> list[str]:
        if self.spec.tls is None:
            return []
        return ["--certs", str(self.spec.tls), "--cert-name", name]

    def start(self) -> None:
        """Start the router, then the work sites, then the pages; return once all are up."""
        spec = self.spec
        self.log_dir.mkdir(parents=True, exist_ok=True)
        if spec.tls is not None:
            make_certificates(spec.tls, spec.site_ids)
        scheme, host = ("tls", "localhost") if spec.tls is not None else ("tcp", "127.0.0.1")
        ports = iter(range(spec.port, 65536, 2)) if spec.port else _free_pairs()
        shared: list[str] = []
        for k in range(spec.routers):
            endpoint = f"{scheme}/{host}:{next(ports)}"
            # Each shared router meshes with those before it and admits every cell.
            name = "router" if k == 0 else f"router-{k + 1}"
            self.routers[name] = RouterPlan(endpoint, tuple(shared), tuple(spec.site_ids))
            shared.append(endpoint)
        if spec.site_routers:
            for site in spec.site_ids:
                endpoint = f"{scheme}/{host}:{next(ports)}"
                self.routers[f"router-{site}"] = RouterPlan(endpoint, tuple(shared), (site,), site)
        for name in self.routers:
            self.start_router(name)
        camera = [] if spec.camera else ["--no-camera"]
        for site in spec.site_ids:  # each listening on loopback, on the next ports
            # The router has checked who sent a command: a work site admits the router's.
            admit = ["--operators", "router"] if spec.tls is not None else []
            self._spawn(
                site,
                [sys.executable, "-m", "work_site", "serve", "--site-id", site,
                 "--listen", f"tcp/127.0.0.1:{next(ports)}",
                 *self._connect(site), *self._certs(work_site_cn(site)), *admit,
                 "--journal", str(self.log_dir / f"{site}.jsonl"),
                 "--vision-rate", str(spec.vision_rate_hz), *camera, *spec.site_args],
            )  # fmt: skip
        for site in spec.site_ids:
            self._wait_for(site, "serving; physics")
        for k, site in enumerate(spec.site_ids[: spec.pages]):
            page_port = spec.page_port + k
            self._spawn(
                f"page-{site}",
                [sys.executable, "-m", "operator_site", "serve", "--site-id", site,
                 *self._connect(), "--client", "--port", str(page_port),
                 *self._certs(operator_cn(site))],
            )  # fmt: skip
            self.pages[site] = f"http://127.0.0.1:{page_port}"

    @property
    def router_endpoints(self) -> list[str]:
        """The shared routers' endpoints (their command ports; state and camera on the next)."""
        return [r.endpoint for r in self.routers.values() if r.site is None]

    @property
    def router_endpoint(self) -> str:
        """The first router's endpoint."""
        return self.router_endpoints[0]

    def _connect(self, site: str | None = None) -> list[str]:
        """``--connect`` options: a work site's to its site router (with site routers), anyone
        else's to every shared router."""
        own = [r.endpoint for r in self.routers.values() if site is not None and r.site == site]
        return [arg for ep in own or self.router_endpoints for arg in ("--connect", ep)]

    def start_router(self, name: str = "router") -> None:
        """Start router ``name`` (again, after :meth:`kill_router`), meshed with the shared
        routers before it; return once it is up."""
        plan = self.routers[name]
        cells = []
        if self.spec.tls is not None:
            for site in plan.sites:
                cells += ["--cell", f"{site}={work_site_cn(site)}:{operator_cn(site)}"]
        self._spawn(
            name,
            [sys.executable, str(REPO / "deploy" / "router.py"),
             str(REPO / "deploy" / "zenoh" / "router.json5"), "--listen", plan.endpoint,
             *(arg for ep in plan.mesh for arg in ("--connect", ep)), *self._certs("router"),
             *cells],
        )  # fmt: skip
        self._wait_for(name, "router: up")

    def kill_router(self, name: str = "router") -> None:
        """SIGKILL router ``name`` (a crash: no goodbye to anyone)."""
        proc = self.procs[name]
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()

    def operator_config(self, site: str) -> zenoh.Config:
        """A zenoh config that reaches the routers as ``site``'s operator (its certificate when
        the fleet has TLS), as a client: everything goes through a router (the first reachable
        of the fleet's)."""
        tls = None if self.spec.tls is None else TlsFiles.in_dir(self.spec.tls, operator_cn(site))
        return make_config(mode="client", connect=link_endpoints(self.router_endpoints)[0], tls=tls)

    def stop(self) -> None:
        """SIGTERM every process (pages and sites before the routers), then wait; kill the
        ones that do not end."""
        for proc in reversed(self.procs.values()):
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGTERM)
        for proc in self.procs.values():
            try:
                proc.wait(timeout=STOP_TIMEOUT_S)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()


def _free_pairs(draws: int = 1000) -> Iterator[int]:
    """Free port pairs (:func:`free_port_pair`), none overlapping another drawn here."""
    taken: set[int] = set()
    for _ in range(draws):
        port = free_port_pair()
        if not taken & {port - 1, port, port + 1}:
            taken |= {port, port + 1}
            yield port
    raise RuntimeError(f"no more distinct free port pairs in {draws} draws")


def make_certificates(out: Path, sites: list[str]) -> None:
    """Certificates for the fleet's cells in ``out`` (``deploy/make-certs.sh``), unless ``out``
    already has a CA and every cell's certificates."""
    names = [n for site in sites for n in (work_site_cn(site), operator_cn(site))]
    if (out / "ca.pem").exists():
        missing = [n for n in names if not (out / f"{n}.pem").exists()]
        if missing:
            raise FileNotFoundError(
                f"{out} has a CA but no certificate for {', '.join(missing)}: remove {out} to "
                "make a new set, or make them with the CA that signed the others"
            )
        return
    subprocess.run(
        [str(REPO / "deploy" / "make-certs.sh"), str(out), *(f"CN:{n}" for n in names)],
        check=True, capture_output=True, text=True,
    )  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    """Start a fleet and keep it up until a signal."""
    parser = argparse.ArgumentParser(prog="fleet", description=__doc__.split("\n\n")[0])
    parser.add_argument("--sites", type=int, default=2, help="work sites (default: %(default)s)")
    parser.add_argument(
        "--routers", type=int, default=1, help="1, or 2 meshed routers (default: %(default)s)"
    )
    parser.add_argument(
        "--site-routers", action="store_true",
        help="each work site behind a router of its own, meshed with the shared routers",
    )  # fmt: skip
    parser.add_argument(
        "--pages", type=int, default=1, help="operator pages, one per cell (default: %(default)s)"
    )
    parser.add_argument(
        "--tls", type=Path, metavar="DIR", help="mutual TLS and per-cell access control"
    )
    parser.add_argument(
        "--port",
        type=int,
        default=7600,
        help="the first router's port and the next; the other routers and the work sites take "
        "the pairs after (default: 7600)",
    )
    parser.add_argument("--page-port", type=int, default=8080, help="the first page's port")
    parser.add_argument("--no-camera", action="store_true", help="work sites without cameras")
    parser.add_argument("--logs", type=Path, help="log directory (default: a temporary one)")
    args = parser.parse_args(argv)
    try:
        spec = FleetSpec(
            sites=args.sites, routers=args.routers, site_routers=args.site_routers,
            pages=args.pages, tls=args.tls, port=args.port,
            page_port=args.page_port, camera=not args.no_camera,
        )  # fmt: skip
    except ValueError as e:
        parser.error(str(e))
    log_dir = args.logs or Path(tempfile.mkdtemp(prefix="fleet-"))

    def on_signal(*_: object) -> None:
        raise KeyboardInterrupt  # also while starting: the Fleet stops what it started

    signal.signal(signal.SIGTERM, on_signal)
    print(f"fleet: starting {spec.routers} router(s) and {spec.sites} work sites; logs in "
          f"{log_dir}", flush=True)  # fmt: skip
    try:
        with Fleet(spec, log_dir) as fleet:
            for name, plan in fleet.routers.items():
                print(f"fleet: {name} on {plan.endpoint} (and the next port)")
            for site in spec.site_ids:
                print(f"fleet: {site}: work site up; page {fleet.pages.get(site, 'none')}")
            print("fleet: up; Ctrl-C stops it all", flush=True)
            while True:
                for name, proc in fleet.procs.items():
                    if proc.poll() is not None:
                        print(f"fleet: {name} ended:\n{fleet.tail(name)}", file=sys.stderr)
                        return 1
                time.sleep(0.5)
    except KeyboardInterrupt:
        pass
    except (RuntimeError, TimeoutError, FileNotFoundError, subprocess.CalledProcessError) as e:
        print(f"fleet: {e}", file=sys.stderr)
        return 1
    print("fleet: stopped", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
