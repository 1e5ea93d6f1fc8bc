"""The capture format (session directory, one MCAP per standpoint) and importers of other recordings."""
