"""rgbdslam: RGB-D visual SLAM in Python."""

__version__ = "0.1.0"


def _defer_open3d_plotly() -> None:
    """``import open3d`` imports ``open3d.visualization.draw_plotly``, which imports plotly, dash
    and IPython: half of Open3D's import time (~1 of 2 s on the 2-core machine), for functions
    rgbdslam never calls. A stand-in module takes its place until one of its functions is called;
    then the real module is imported and called. Nothing happens when Open3D is already imported."""
    import sys

    name = "open3d.visualization.draw_plotly"
    if "open3d" in sys.modules or name in sys.modules:
        return
    import types

    stand_in = types.ModuleType(name, "stands for Open3D's draw_plotly until first used (rgbdslam/__init__.py)")

    def deferred(attr: str):
        def call(*args, **kwargs):
            import importlib

            if sys.modules.get(name) is stand_in:
                del sys.modules[name]
            return getattr(importlib.import_module(name), attr)(*args, **kwargs)

        call.__name__ = attr
        return call

    for attr in ("get_plotly_fig", "draw_plotly", "draw_plotly_server"):
        setattr(stand_in, attr, deferred(attr))
    sys.modules[name] = stand_in


_defer_open3d_plotly()
