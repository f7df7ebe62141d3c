"""Cross-cutting concerns: settings, logging, errors."""
