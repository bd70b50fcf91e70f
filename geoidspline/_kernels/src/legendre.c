/* Kernels of legendre (geoidspline/_kernels/legendre.py calls them through ctypes). */
#include "gs_common.h"
