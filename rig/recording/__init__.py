"""MCAP recording: schemas, the packed tick codec, the writer process, segments."""
