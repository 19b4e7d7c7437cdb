"""Synthetic scenes and pairs with known truth (trajectory, changes, gain, depth)."""
