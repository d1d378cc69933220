"""realgap slam package."""
