"""tether, the application: the CLI, runs, sweeps and reports, placement in a
user's scene, and the wiring of the tuning page and the viewer. It composes
the layers below (estimation, sim, controllers, viz). :mod:`tether.catalog`
registers the built-in strategy kinds and scenarios with :mod:`sim`; the
modules that need them import it (``import tether.catalog`` in your own
code). This package itself imports nothing, so that the command's entry
point (:mod:`tether.entry`) takes the signals before the heavy imports."""
