"""The revisions of the fleet history's schema, oldest first."""
