"""Where runs live: run files written as they are acquired, and the run catalog."""
