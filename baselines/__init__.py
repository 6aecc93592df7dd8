"""The 4DGS host framework: rasterizer, dataset readers, scene simulator and the 4DGS baseline."""
