"""Stage 0 of the home robot: it explores and maps its home before it takes commands."""
