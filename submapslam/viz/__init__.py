"""Live views of a run (optional extras; nothing here is imported by the library's core)."""
