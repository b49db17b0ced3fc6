"""Sparse-graph TOA: graph structure, start, fit and checks."""
