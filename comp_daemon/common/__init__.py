"""Small helpers every layer may use: atomic file writes, files a user names, structured logging."""
