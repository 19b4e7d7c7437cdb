"""One intensity scale for both images, and clipped pixels (METHOD.md section 7).

eq. 13's ``lambda_chi`` and the change threshold only mean something on a
known scale, yet inputs come as 8-bit, 12-bit in 16-bit, 16-bit or float in
any units, with any offset.  The rule, applied to the reference and the
capture alike:

1. **Clipped pixels.**  A pixel at a sensor's saturation value or at zero
   says only that the scene was at least (at most) that bright: it is left
   out of the row solves and is a bound of the change test
   (:mod:`ops.changes._bounds`).  On the ingested luminance (integers divided
   by their dtype's maximum, floats as they are) an image's largest valid
   value is a saturation value when it is 1 (an integer input at its
   dtype's maximum, or float data on [0, 1]) or ``(2**k - 1) / 65535`` for k
   from 10 to 15 (a k-bit sensor stored in 16 bits); its smallest is a floor
   when it is 0.  Pixels at a saturation value or a floor are clipped.  Float
   data in other units carry no clip level (nothing says where they
   saturate), and the brightest object of an image is not clipped unless it
   sits at such a value.
   Zeros that are fill, not dark scene, are no-data (:func:`fill_zeros`):
   a 0 region that reaches the image's edge or no-data, or holds a
   :data:`FILL_SQUARE` px square of zeros (the black collar of an untagged
   orthophoto), with the zeros joined to it within :data:`FILL_REACH` px;
   scattered dark pixels inside the image stay clipped values (bounds).
2. **One scale.**  From the valid, unclipped values of *both* images pooled:
   ``x' = x * SPAN / (hi - lo)`` with ``lo`` and ``hi`` their
   :data:`LOW_PERCENTILE` and :data:`HIGH_PERCENTILE`: residuals are
   fractions of the scene's range, whatever the bit depth or units.
   :data:`SPAN` is the range of a typical 8-bit aerial photograph on [0, 1],
   for which ``lambda_chi`` and the threshold's floor were tuned.  The map is linear, not affine: zero stays
   zero, so a gain between the images stays a pure gain (``||w||_1``; eq. 13
   has no offset term).  An offset of the units (float data with a pedestal)
   stays in both images and cancels between them; under a gain it leaves an
   offset that eq. 13 cannot model (the rows' gains absorb it).
"""

from dataclasses import dataclass

import cv2
import numpy as np
from scipy import ndimage

from ._errors import InputError

__all__ = ["FILL_REACH", "FILL_SQUARE", "IntensityScale", "fill_zeros", "intensity_scale"]

LOW_PERCENTILE = 0.1
HIGH_PERCENTILE = 99.9
SPAN = 0.8
#: Side (px) of a square of zeros that makes a 0 region fill (no-data).
FILL_SQUARE = 24
#: Zeros joined (through zeros, px) to fill within this distance are fill.
FILL_REACH = 48


@dataclass(frozen=True)
class IntensityScale:
    """The map of both images onto one scale, and their clip levels.

    Attributes
    ----------
    lo, hi : float
        The pooled percentiles: inputs are multiplied by ``SPAN / (hi - lo)``.
    reference_clip, capture_clip : tuple of float or None
        (floor, saturation) of each image, None where it has none: pixels at
        or beyond them are clipped.
    reference_clipped, capture_clipped : float
        Fraction of each image's valid pixels that are clipped.
    """

    lo: float
    hi: float
    reference_clip: tuple
    capture_clip: tuple
    reference_clipped: float = 0.0
    capture_clipped: float = 0.0

    def apply(self, values, image):
        """``values`` (float32, NaN for no-data) of ``image`` ("reference" or
        "capture") on the common scale, NaN where clipped or no-data."""
        values = np.asarray(values, dtype=np.float32)
        return self._without_clipped(values * np.float32(SPAN / (self.hi - self.lo)), values, values, image)

    def cell_means(self, sums, lows, highs, count, image):
        """The means of cells of ``count`` ingested values of ``image`` each,
        from their sums (float64, NaN where a cell holds no-data) and their
        least and largest values, on the common scale: float32, NaN where a
        cell holds no-data or a clipped value (see :meth:`apply`).  Cells of
        one value are :meth:`apply`'s values, bit for bit."""
        out = np.asarray(sums, np.float64) / count * np.float64(np.float32(SPAN / (self.hi - self.lo)))
        return self._without_clipped(out.astype(np.float32), np.asarray(lows), np.asarray(highs), image)

    def _without_clipped(self, out, lows, highs, image):
        """``out`` with NaN where ``lows`` reach ``image``'s floor or ``highs``
        its saturation (the clip rule of :meth:`apply`)."""
        low, high = self.reference_clip if image == "reference" else self.capture_clip
        if low is not None:
            out[lows <= np.float32(low)] = np.nan
        if high is not None:
            out[highs >= np.float32(high)] = np.nan
        return out

    def scaled(self, value):
        """One ingested value (a clip level) on the common scale."""
        return float(np.float32(value) * np.float32(SPAN / (self.hi - self.lo)))

    def to_input(self, values):
        """Values on the common scale back in the ingested units."""
        return np.asarray(values, dtype=np.float32) * np.float32((self.hi - self.lo) / SPAN)

    def as_dict(self):
        return {"rule": f"x' = x * {SPAN} / (hi - lo) from the pooled unclipped values of both images "
                        f"(percentiles {LOW_PERCENTILE} and {HIGH_PERCENTILE}); pixels at a saturation value "
                        "(1, or (2**k - 1) / 65535 for k in 10..15) or at 0 are clipped (left out of the row solves; "
                        "bounds of the change test); zeros that reach the image's edge or no-data, or hold a "
                        f"{FILL_SQUARE} px square, and zeros joined to them within {FILL_REACH} px are fill (no-data)",
                "lo": self.lo, "hi": self.hi, "reference_clip": list(self.reference_clip),
                "capture_clip": list(self.capture_clip), "reference_clipped": self.reference_clipped,
                "capture_clipped": self.capture_clipped}

    @classmethod
    def from_dict(cls, values):
        return cls(float(values["lo"]), float(values["hi"]), tuple(values["reference_clip"]),
                   tuple(values["capture_clip"]), float(values["reference_clipped"]),
                   float(values["capture_clipped"]))


#: Saturation values of the ingested luminance: 1 (an integer at its dtype's
#: maximum, float data on [0, 1]) and those of k-bit sensors stored in 16 bits.
SATURATION = (1.0,) + tuple(float(np.float32(2 ** k - 1) / np.float32(65535)) for k in range(10, 16))


def _clip_levels(stats):
    """(floor or None, saturation or None) of an image from its value range."""
    low = 0.0 if stats.low == 0.0 else None
    high = next((v for v in SATURATION if abs(stats.high - v) <= 1e-6 * v), None)
    return low, None if high is None else stats.high


def intensity_scale(reference, capture, *, names=("reference", "capture")):
    """The common scale of two images from their statistics.

    Parameters
    ----------
    reference, capture : object
        Each with ``count``, ``low``, ``high`` (valid values and their range),
        ``at_low``, ``at_high`` (how many sit at each end) and ``sample`` (a
        sample of the valid values), e.g. :class:`rsmb.tiles.WindowStats`.
    names : tuple of str
        How errors name the two images.

    Returns
    -------
    IntensityScale

    Raises
    ------
    InputError
        When an image has nothing left once its clipped pixels are set aside.
    """
    pooled, levels, clipped = [], [], []
    for stats, name in zip((reference, capture), names):
        low, high = _clip_levels(stats)
        sample = np.asarray(stats.sample, dtype=np.float64)
        keep = np.ones(sample.shape, bool)
        count = 0
        if low is not None:
            keep &= sample > low
            count += stats.at_low
        if high is not None:
            keep &= sample < high
            count += stats.at_high
        if not keep.any() or count >= stats.count:
            raise InputError(f"{name}: every valid pixel is clipped (at zero or at its saturation value)")
        pooled.append(sample[keep])
        levels.append((low, high))
        clipped.append(count / stats.count)
    values = np.concatenate(pooled)
    lo, hi = (float(v) for v in np.percentile(values, [LOW_PERCENTILE, HIGH_PERCENTILE]))
    if not hi > lo:
        lo, hi = float(values.min()), float(values.max())
    if not hi > lo:
        hi = lo + 1.0
    return IntensityScale(lo, hi, levels[0], levels[1], clipped[0], clipped[1])


def _squares(mask, side):
    """The union of the ``side`` x ``side`` squares of ``mask`` (bool) that
    lie within it: an opening, its erosion anchored at the square's centre
    and its dilation at the mirrored point, so that an even side shifts
    nothing (cv2 anchors both at the same point)."""
    square = np.ones((side, side), np.uint8)
    centre, mirrored = side // 2, (side - 1) // 2
    inside = cv2.erode(mask.astype(np.uint8), square, anchor=(centre, centre), borderType=cv2.BORDER_CONSTANT,
                       borderValue=0)
    return cv2.dilate(inside, square, anchor=(mirrored, mirrored), borderType=cv2.BORDER_CONSTANT, borderValue=0) > 0


def fill_zeros(values):
    """The zeros of an image window that are fill, not dark scene.

    A 0 region is fill when it touches the image's edge or no-data, or holds
    a :data:`FILL_SQUARE` x :data:`FILL_SQUARE` square of zeros; its zeros
    joined to such pixels through zeros within :data:`FILL_REACH` px are
    fill too.  Local: a window grown by ``FILL_SQUARE + FILL_REACH`` px on
    every side decides its core as the whole image does.

    Parameters
    ----------
    values : ndarray, shape (H, W), float32
        NaN for no-data and beyond the image.

    Returns
    -------
    ndarray of bool, shape (H, W)
    """
    values = np.asarray(values, np.float32)
    zero = values == 0
    if not zero.any():
        return zero
    ring = np.ones((3, 3), np.uint8)
    seed = zero & (cv2.dilate((~np.isfinite(values)).astype(np.uint8), ring) > 0)
    seed |= _squares(zero, FILL_SQUARE)
    if not seed.any():
        return seed
    # the 0 regions (8-connected); only those holding a seed are visited
    _, labels = cv2.connectedComponents(zero.view(np.uint8), connectivity=8, ltype=cv2.CV_32S)
    boxes = ndimage.find_objects(labels)
    out = seed.copy()
    for k in np.unique(labels[seed]):
        box = boxes[k - 1]
        part = labels[box] == k
        out[box] |= ndimage.binary_dilation(seed[box] & part, structure=np.ones((3, 3), bool),
                                            iterations=FILL_REACH, mask=part)
    return out
