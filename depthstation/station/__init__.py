"""The station as a whole: demo, viewer, comparison of result folders."""
