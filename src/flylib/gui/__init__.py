"""``flylib gui``: review a recording's 3D pose in the browser, fix it, save the fixes.

A FastAPI app (:func:`create_app`) over a :class:`ReviewSession` (one recording's ``results.h5``,
footage and ``corrections.h5`` sidecar), served by uvicorn (:func:`serve`); the front-end is static
ES modules in ``static/``. FastAPI and uvicorn are imported only when the GUI is used."""

import lazy_loader as _lazy

# The names and their modules are listed once, in ``__init__.pyi``.
__getattr__, __dir__, __all__ = _lazy.attach_stub(__name__, __file__)
