"""Writing results: figures, JSON/CSV numbers and self-contained HTML pages."""
