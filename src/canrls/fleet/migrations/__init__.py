"""The Alembic migrations of the fleet history's schema (:mod:`canrls.fleet.history`)."""
