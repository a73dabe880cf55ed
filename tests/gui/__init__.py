"""``flylib gui``: its app, server, journal, security and the page in a browser."""
