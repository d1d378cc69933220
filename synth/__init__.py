"""realgap synth package."""
