"""From frames to a 3D map: streamed frame sources and their intrinsics, per-frame depth and a chained camera
path from a trained model, and TSDF fusion of the two into a surface (``endoflow reconstruct``)."""
