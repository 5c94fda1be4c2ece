"""The dashboard's routers, one per concern; :func:`layerwatch.web.app.create_app` includes them all."""
