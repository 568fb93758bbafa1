"""Schema migrations of the job store (Alembic), run when a :class:`~service.jobs.JobStore` opens.

The revisions live in ``versions/`` inside the package (shipped in the wheel),
and are run programmatically: no ``alembic.ini``. A database made before
migrations existed (the ``jobs`` table made by ``create_all``, no
``alembic_version`` table) is the first revision's layout: it is stamped as
such, then upgraded like any other, and its rows are kept.

Add a revision: write ``versions/NNNN_<what>.py`` with ``revision`` =
``"NNNN"`` and ``down_revision`` = the previous one (``alembic revision``
needs an ini file; copying the last revision is simpler), and never edit a
released one.
"""

from __future__ import annotations

import sqlalchemy as sa
from sqlalchemy.engine import Engine

__all__ = ["BASELINE", "current_revision", "upgrade"]

BASELINE = "0001"  # the layout of databases made before migrations (create_all)
_LOCATION = "service:migrations"


def _config(connection: sa.Connection):
    from alembic.config import Config

    cfg = Config()
    cfg.set_main_option("script_location", _LOCATION)
    cfg.attributes["connection"] = connection
    return cfg


def current_revision(engine: Engine) -> str | None:
    """The revision the database is at (None: empty, or made before migrations)."""
    from alembic.runtime.migration import MigrationContext

    with engine.connect() as conn:
        return MigrationContext.configure(conn).get_current_revision()


def upgrade(engine: Engine, revision: str = "head") -> None:
    """Bring the database to ``revision``; a pre-migration database is stamped as :data:`BASELINE` first."""
    from alembic import command

    with engine.begin() as conn:
        tables = set(sa.inspect(conn).get_table_names())
        cfg = _config(conn)
        if "jobs" in tables and "alembic_version" not in tables:
            command.stamp(cfg, BASELINE)
        command.upgrade(cfg, revision)
