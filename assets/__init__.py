"""Data files: MJCF robot models, probe geometry, phantom specification."""
