"""Captures and their files on disk: the Capture object, its meta.json and that file's schema."""
