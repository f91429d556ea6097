"""dashboard tier."""
