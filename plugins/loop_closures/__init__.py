"""Loop-closure plugins (`loop_closure=NAME`): `none` and `pose_graph`."""
