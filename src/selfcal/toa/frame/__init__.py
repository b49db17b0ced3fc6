"""The user frame: known nodes, node bookkeeping, the framed result."""
