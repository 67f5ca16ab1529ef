"""Comparison sweeps: variants of one stage over seeds (``spec`` the file, ``runner`` the runs, ``results`` the
table)."""
