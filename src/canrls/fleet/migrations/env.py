"""Alembic's environment for the fleet history: migrations run on the connection that
:meth:`canrls.fleet.history.History.open` hands over (no alembic.ini, no URL here)."""

from __future__ import annotations

from alembic import context

from canrls.fleet.history import METADATA

connection = context.config.attributes.get("connection")
if connection is None:
    raise RuntimeError("the fleet history's migrations run through "
                       "canrls.fleet.history.History.open")
context.configure(connection=connection, target_metadata=METADATA(),
                  render_as_batch=connection.dialect.name == "sqlite")
with context.begin_transaction():
    context.run_migrations()
