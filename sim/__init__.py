"""tether simulator: scenarios, world assembly, sensing, the step loop, CLI."""

from sim.gl import choose_gl_backend

choose_gl_backend()
