"""curlnav replay: see README."""
