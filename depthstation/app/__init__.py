"""The application on top of the stages: the console script, the demo, view and compare."""
