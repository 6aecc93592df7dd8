"""Dataset readers (nvidia, dnerf, hypernerf, colmap) producing cameras in our convention."""
