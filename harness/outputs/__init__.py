"""Episode outputs: the sinks that turn finished step records into files (writers), the pictures they draw (overlays, video)."""
