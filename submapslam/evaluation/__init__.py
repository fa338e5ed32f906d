"""Evaluation: trajectory metrics (no I/O) and comparison reports (matplotlib only here)."""
