"""One router per resource, each mounted under ``/api/v1`` by :func:`eyeserver.api.create_app`."""
