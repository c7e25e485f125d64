"""python-can buses: opening SocketCAN / virtual / socket-pair buses, error
classification."""
