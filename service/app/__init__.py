"""The use cases, the one place the CLI and the HTTP service call (docs/architecture.md)."""
