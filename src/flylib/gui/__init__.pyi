"""flylib.gui's names and the modules they come from.

``flylib/gui/__init__.py`` reads this file (``lazy_loader.attach_stub``) and loads each
module on first use of one of its names: FastAPI and uvicorn only when the GUI is used.
"""

from .app import create_app as create_app
from .server import serve as serve
from .session import ReviewSession as ReviewSession, resolve_results as resolve_results
