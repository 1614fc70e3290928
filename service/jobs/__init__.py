"""Work in other processes: the job runner, its workers and kincal serve's process tree
(docs/architecture.md)."""
