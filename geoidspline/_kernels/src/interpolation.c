/* Kernels of interpolation (geoidspline/_kernels/interpolation.py calls them through ctypes). */
#include "gs_common.h"
