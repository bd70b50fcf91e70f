"""The packed key layout every kernel and :mod:`geoidspline.bspline.keys` share.

Coefficient indices are packed into one int64 key, :data:`KEY_BITS` bits an axis, each
index offset by :data:`KEY_OFFSET` so that it is non-negative. Plain integers (no compiled code):
the numeric bottom of the package, imported by the numpy key helpers above it too.
"""

KEY_BITS = 21

KEY_OFFSET = 1 << (KEY_BITS - 1)
