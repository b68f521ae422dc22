"""Input formats: one module per format."""
