"""colonyd package."""
