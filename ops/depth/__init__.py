"""Depth: the paper's depth layers per component, the dense depth map of what the plane
leaves unexplained, and the rows re-solved at each pixel's depth."""
