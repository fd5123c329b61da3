"""What the loop hands out besides commands: recordings, the live Foxglove server, the annotated view."""
