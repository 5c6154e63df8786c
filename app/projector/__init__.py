"""The projector template (DESIGN.md "The projector template", issue 7).

Modules, in the direction of their imports:

- :mod:`app.projector.model`    the projector as an inverse pinhole camera (K_p, size, T_camera_projector)
- :mod:`app.projector.geometry` numpy ray casting and point-to-mesh distances (no GL)
- :mod:`app.projector.plan`     plans in the bone frame: files (mesh, YAML polylines) and the demo shapes
- :mod:`app.projector.render`   moderngl: the template seen from the projector, hidden parts removed
- :mod:`app.projector.view`     the safety gate (status ok and fresh, else a warning pattern)
- :mod:`app.projector.output`   PNG files and the full-screen window (pyglet, imported lazily)
- :mod:`app.projector.accuracy` tracing lit pixels back to the bone; template error in mm
- :mod:`app.projector.rerun_log` the projector frustum and image in rerun
- :mod:`app.projector.config`   the ``projector:`` YAML block (configs/projector.yaml)
"""
