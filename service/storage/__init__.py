"""Storage of the HTTP service: database rows (SQLAlchemy 2) and atomically written files."""
