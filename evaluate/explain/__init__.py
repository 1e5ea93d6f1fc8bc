"""Explain: locate sim-vs-real mismatches, attribute them to catalogue effects, refit, show."""
