"""realgap app package."""
