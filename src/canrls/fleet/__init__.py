"""Many drives: their logs ingested on Dask, their parameters kept in a history, wear found.

* :mod:`canrls.fleet.sources`: which logs belong to which drive (a glob with a
  ``{drive}`` field, or a manifest CSV);
* :mod:`canrls.fleet.ingest`: each log through the same pipeline as ``canrls fit``, on
  a Dask cluster or in this process, into the history, each recording once;
* :mod:`canrls.fleet.history`: the history (SQLAlchemy; SQLite or PostgreSQL), its
  schema versioned by the Alembic migrations in ``migrations/``;
* :mod:`canrls.fleet.detect`: change, drift and outlier detection that respects each
  recording's sigma; :mod:`canrls.fleet.fleet_report`: the HTML page and the JSON.

``docs/fleet.md`` has the commands, the schema and the statistics.
"""
