"""``rsmb detect``: the plan, the tile tasks, the overview and slow part, trajectory
fusion and the store's outputs."""
