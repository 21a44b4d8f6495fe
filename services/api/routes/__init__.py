"""The API's routers, one per resource; :func:`services.api.app.create_app` includes them."""
