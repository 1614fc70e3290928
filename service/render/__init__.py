"""Results out: the result document, text, HTML, plots and controller exports
(docs/architecture.md)."""
