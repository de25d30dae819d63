"""What crosses the wire, in HTTP bodies and in frame bundles' files: the JSON models, the
binary layouts and the scenes they decode to, and the problem documents of errors. Plain
numpy and Pydantic: no FastAPI app, no engine."""
