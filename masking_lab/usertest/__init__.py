"""usertest."""
