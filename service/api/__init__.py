"""HTTP routes of API v1 (``shared/design/api-v1.md``)."""
