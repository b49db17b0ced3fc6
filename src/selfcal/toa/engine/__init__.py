"""The least-squares engines of the TOA model: model, refinement, covariance, CRLB."""
