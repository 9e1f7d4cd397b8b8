"""curlnav scheduler: see README."""
