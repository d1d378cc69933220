"""realgap recog package."""
