"""Bundle adjustment: refine the camera rig against the fly's own detected joints.

- ``adjust``: :func:`bundle_adjust` on one flattened problem (outlier rounds, distortion policy);
- ``messages``: its warnings in plain words, the logged summary and the ``report``;
- ``sequence``: :func:`bundle_adjust_sequence` on a recording's ``(V, T, P, 2)`` detections
  (frames, bone lengths, rigid points);
- ``unknowns``: shared 3D unknowns (rigid points) and bone rows of a flattened problem;
- ``params``: the ``fixed`` / ``shared`` parameter grammar;
- ``sampling``: ``frame_sampling``, which frames the fit uses (a recording's or a session's);
- ``problem``: residuals, the JAX Jacobian as a sparse matrix, the ``scipy`` path;
- ``lm``: Levenberg-Marquardt on the reduced camera system (Schur complement);
- ``reseed``: PnP re-seeding of grossly-off cameras, the radial-fold check;
- ``gauge``: the similarity gauge held during a fit and the frame the result is reported in;
- ``parts``: camera groups that share no view."""

import lazy_loader as _lazy

# Names and modules are listed in ``__init__.pyi``: JAX and SciPy load with the solver, not
# with the parameter grammar (``params``) that planning reads for every run and cluster job.
__getattr__, __dir__, __all__ = _lazy.attach_stub(__name__, __file__)
