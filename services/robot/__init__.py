"""robot tier."""
