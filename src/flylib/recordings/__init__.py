"""Recordings: which directories hold footage for every configured source, and where results go.

A *recording* is a directory holding footage for every ``[[sources]]`` entry of the config: one
video, or one image sequence, per source, all with the same frame count. :func:`find_recording`
resolves one directory (:mod:`.footage`; video frame counts cached by :mod:`.frame_counts`);
:func:`resolve_recordings` expands literal paths and wildcard patterns (optionally recursively) into
a batch; :func:`plan_listing` turns a ``recordings`` listing (paths, patterns, per-recording
mappings or a ``.tsv`` / ``.csv`` sheet, :mod:`.sheets`) into :class:`Recording` objects with
stable, unique ids and output directories (:mod:`.listing`; a path that finds nothing is explained
by :mod:`.lookup`). The workflow plans its jobs from
:func:`flylib.pipeline.planning.plan_recordings`.
"""

from .footage import find_recording
from .listing import Recording, plan_listing, resolve_recordings

__all__ = ["Recording", "find_recording", "plan_listing", "resolve_recordings"]
