"""curlnav learner: see README."""
