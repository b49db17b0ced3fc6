"""The statistical verdicts on a TOA fit: trust, determinacy, selection, uniqueness."""
