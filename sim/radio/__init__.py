"""tether's radio channel: pure formulas (``channel``) and parameter presets (``presets``).

Nothing here imports MuJoCo or touches the scene: callers pass distances, wall
counts and random generators in, and get dB, probabilities and seconds back.
"""
