"""Images, output files and render statistics."""
