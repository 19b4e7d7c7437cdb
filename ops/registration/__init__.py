"""Registration of a capture against a reference: eq. 13 per row (the fast solver and its
problems), the start search, propagation along the rows, gain, the slow yaw/pitch part
and the re-solve of rows a raised structure pulled off the ground."""
