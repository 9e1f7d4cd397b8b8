"""curlnav proto: see README."""
