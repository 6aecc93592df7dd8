"""The web viewer of trained runs (view.py), on viser.

Modules, one job each: `cli` (flags, input checks), `app` (the viser server, its controls, the
camera frustums, side-by-side pictures), `render_loop` (per-browser thread: low resolution
while moving, full once still), `runs` (a loaded run: cached deformed states, selections,
modes), `frame` (what a render mode receives; RGB, depth, alpha), `camera` (browser camera <->
viewmat/K). nerfview (viser's companion used by gsplat's simple_viewer) is not used: its 0.1.3
release imports jaxtyping, splines and torch without declaring them, and exits the process on
any exception in a render.
"""
