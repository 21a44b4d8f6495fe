"""The REST API (FastAPI): read-only status for everyone, creating and cancelling experiments with a token.

Serve it with ``uvicorn services.api.app:app``. It imports neither torch nor bpy.
"""
