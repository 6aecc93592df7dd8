"""Standard exports of a trained 4D model: per-time 3DGS PLYs and 3D tracks.

    python -m baselines.export -m RUN --times 0 0.5 1 --format ply -o OUT     # OUT/point_cloud_t0.5000.ply ...
    python -m baselines.export -m RUN --format tracks -o OUT                  # OUT/tracks.npz + OUT/tracks_test.mp4
    python -m baselines.export.track_eval OUT/tracks.npz -s DATASET           # tracks vs ground-truth flow

Modules: `cli` (the command), `tracks` (centres over time, visibility, the npz), `track_video`
(the trails over rendered views), `track_eval` (against the simulator's ground-truth flow). The
PLY writer is the checkpoint's (`baselines.fourdgs.checkpoint.state_to_ply`): the deformed state
at a time, in the layout Inria's 3DGS viewers read.
"""
