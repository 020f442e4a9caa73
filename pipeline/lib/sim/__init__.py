"""The digital twin: a virtual UR5 as wrong as a real one, its campaign files, driving it, and
how hard a campaign is."""
