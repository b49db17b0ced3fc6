"""Recipes: preprocessing and the common-offset and other prepared solves."""
