/* The Python module shell of geoidspline's compiled kernels. The kernels are plain C
 * functions called through ctypes (geoidspline/_kernels/_clib.py), which releases the GIL
 * for the call; importing this module only lets Python's import system find the file,
 * wherever the package is installed. */
#define PY_SSIZE_T_CLEAN
#include <Python.h>

static struct PyModuleDef gs_module = {
    PyModuleDef_HEAD_INIT, "_libkernels",
    "geoidspline's compiled kernels (C, called through ctypes: see geoidspline._kernels._clib).", -1, NULL,
};

PyMODINIT_FUNC PyInit__libkernels(void)
{
    return PyModule_Create(&gs_module);
}
