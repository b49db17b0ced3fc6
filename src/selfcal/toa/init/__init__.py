"""TOA initialisers (one per file) and their registry (``starts``)."""
