"""A throwaway PostgreSQL server for the tests: ``initdb`` into a temporary folder, ``pg_ctl
start`` on 127.0.0.1 and a free port, ``pg_ctl stop -m immediate`` at the end.

The server binaries come with Debian's ``postgresql`` package (``setup.sh`` installs it):
``/usr/lib/postgresql/<version>/bin``. ``initdb`` and ``postgres`` refuse to run as root, so
as root they run as the ``postgres`` system user (made by that package) through ``runuser``,
in a folder it owns. Without the binaries (or the driver, ``psycopg``) the tests that need
a server fail with the reason when ``CI`` or ``POSECAL_REQUIRE_PG`` is set, and are skipped
otherwise (:func:`unavailable`).
"""

from __future__ import annotations

import glob
import importlib.util
import os
import pwd
import shutil
import subprocess
import tempfile
from pathlib import Path

from service.server import free_port

__all__ = ["PostgresServer", "find_bin", "required", "unavailable"]

_USER = "postgres"  # the system user of Debian's package, for running the server as root
_TIMEOUT_S = 120.0  # any one command (initdb, start, stop)


def find_bin() -> Path | None:
    """The newest ``/usr/lib/postgresql/*/bin`` holding initdb, pg_ctl and postgres (None: none)."""
    found = [Path(d) for d in glob.glob("/usr/lib/postgresql/*/bin")
             if all(os.access(Path(d) / tool, os.X_OK) for tool in ("initdb", "pg_ctl", "postgres"))]
    return max(found, key=lambda d: int(d.parent.name) if d.parent.name.isdigit() else 0, default=None)


def required() -> bool:
    """Whether a missing server is a failure (CI) rather than a reason to skip."""
    return bool(os.environ.get("CI") or os.environ.get("POSECAL_REQUIRE_PG"))


def unavailable() -> str | None:
    """Why no server can be started here, or None if one can."""
    if find_bin() is None:
        return ("no PostgreSQL server binaries (initdb, pg_ctl, postgres) in /usr/lib/postgresql/*/bin: "
                "install Debian's postgresql package (./setup.sh does)")
    if importlib.util.find_spec("psycopg") is None:
        return "no PostgreSQL driver: pip install 'posecal[postgres]' (./setup.sh does)"
    if os.geteuid() == 0:
        try:
            pwd.getpwnam(_USER)
        except KeyError:
            return f"running as root, and there is no {_USER!r} user to run the server as"
        if shutil.which("runuser") is None:
            return "running as root without runuser (util-linux) to run the server as another user"
    return None


class PostgresServer:
    """One server in a temporary folder; ``url(db)`` gives a SQLAlchemy URL (psycopg) to it."""

    def __init__(self) -> None:
        self.bin = find_bin()
        if self.bin is None:
            raise RuntimeError(unavailable())
        # Under the system temp directory, not pytest's (root-only) one: the server's user must reach it.
        self.root = Path(tempfile.mkdtemp(prefix="posecal-pg-"))
        self.data, self.log = self.root / "data", self.root / "server.log"
        self.port = 0
        self._as_user: list[str] = []
        if os.geteuid() == 0:
            user = pwd.getpwnam(_USER)
            os.chown(self.root, user.pw_uid, user.pw_gid)
            self._as_user = ["runuser", "-u", _USER, "--"]

    def _run(self, tool: str, *args: str) -> None:
        cmd = [*self._as_user, str(self.bin / tool), *args]
        done = subprocess.run(cmd, capture_output=True, text=True, timeout=_TIMEOUT_S, cwd=self.root)
        if done.returncode != 0:
            log = self.log.read_text()[-2000:] if self.log.exists() else ""
            raise RuntimeError(f"{tool} failed ({done.returncode}): {done.stderr.strip()[-2000:]}\n{log}")

    def start(self) -> "PostgresServer":
        """initdb (trust authentication, user ``posecal``, no fsync) and start on 127.0.0.1."""
        self._run("initdb", "-D", str(self.data), "-U", "posecal", "-A", "trust", "-E", "UTF8",
                  "--locale=C", "--no-sync")
        self.port = free_port()
        options = f"-k {self.root} -h 127.0.0.1 -p {self.port} -F -c max_connections=200"
        self._run("pg_ctl", "start", "-D", str(self.data), "-l", str(self.log), "-w", "-t", "60",
                  "-o", options)
        return self

    def url(self, database: str = "postgres") -> str:
        return f"postgresql+psycopg://posecal@127.0.0.1:{self.port}/{database}"

    def create_database(self, name: str) -> str:
        """A new empty database; returns its URL."""
        import sqlalchemy as sa

        engine = sa.create_engine(self.url(), isolation_level="AUTOCOMMIT")
        try:
            with engine.connect() as conn:
                conn.execute(sa.text(f'CREATE DATABASE "{name}"'))
        finally:
            engine.dispose()
        return self.url(name)

    def stop(self) -> None:
        """Stop at once (``-m immediate``) and remove the folder."""
        try:
            if (self.data / "postmaster.pid").exists():
                self._run("pg_ctl", "stop", "-D", str(self.data), "-m", "immediate", "-w", "-t", "30")
        finally:
            shutil.rmtree(self.root, ignore_errors=True)
