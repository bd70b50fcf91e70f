/* Kernels of query (geoidspline/_kernels/query.py calls them through ctypes). */
#include "gs_common.h"
