"""tether, the application: the CLI, runs, sweeps and reports, placement in a
user's scene, and the wiring of the tuning page and the viewer. It composes
the layers below (estimation, sim, controllers, viz) and registers the
built-in strategy kinds and scenarios with :mod:`sim` on import."""

from tether import catalog as _catalog  # noqa: F401 (registers the built-ins)
