"""The HTTP layer: the FastAPI app (`app.create_app` wires it), one router per resource
under routes/, the middleware that guards every request, the problems a failure becomes,
and the uvicorn server that drops slow clients."""
