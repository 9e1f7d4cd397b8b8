"""curlnav actor: see README."""
