"""File formats: TUM lists and trajectories (`tum`), 3DGS PLY maps (`ply`), RGB-D image folders
(`images`) and trajectory plots (`plots`)."""
