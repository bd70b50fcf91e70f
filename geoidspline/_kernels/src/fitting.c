/* Kernels of fitting (geoidspline/_kernels/fitting.py calls them through ctypes). */
#include "gs_common.h"
