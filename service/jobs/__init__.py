"""Reconstruction jobs: a SQLite store with files on disk, and worker processes that run them."""
