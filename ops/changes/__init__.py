"""Changes: the change score, thresholds, masks and components, the reference-grid
mapping, and the metrics against known truth."""
