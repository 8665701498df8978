"""The HTTP service: the FastAPI app (api), the job manager and its events (jobs),
admission limits, settings, response schemas, the live pages and the uvicorn server."""
