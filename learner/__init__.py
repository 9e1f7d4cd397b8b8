"""curlnav learner: the D4PG core (config, networks, update) and its service shell."""
