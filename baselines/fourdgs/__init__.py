"""4DGS baseline: Gaussian model, HexPlane deformation, trainer loop, hooks, plugins, checkpoints."""
