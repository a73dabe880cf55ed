"""``flylib gui``: review a recording's 3D pose in the browser, fix it, save the fixes.

A FastAPI app (:func:`create_app`) over a :class:`ReviewSession` (one recording's
``results.h5``, footage and ``corrections.h5`` sidecar), served by uvicorn
(:func:`serve`); the front-end is static ES modules in ``static/``. FastAPI and
uvicorn are imported only when the GUI is used.
"""

from .session import ReviewSession, resolve_results

__all__ = ["ReviewSession", "create_app", "resolve_results", "serve"]


def __getattr__(name):
    if name == "create_app":
        from .app import create_app

        return create_app
    if name == "serve":
        from .server import serve

        return serve
    raise AttributeError(name)
