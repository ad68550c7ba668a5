"""lift stage."""
