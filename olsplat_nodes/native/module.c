/* The Python side of olsplat's C kernels (heatmap_composite.c, topk_composite.c, winning_rows.c): an empty module,
 * so that setuptools builds and installs them as one extension; ``native/__init__.py`` loads the
 * same file with ctypes. */
#include <Python.h>

/* 1 when this build uses AVX2, FMA and F16C instructions: the loader then checks that the CPU has them. */
int built_with_avx2(void)
{
#if defined(__AVX2__) && defined(__FMA__) && defined(__F16C__)
    return 1;
#else
    return 0;
#endif
}

static struct PyModuleDef kernels_module = {PyModuleDef_HEAD_INIT, "_kernels",
                                            "olsplat's C kernels, loaded with ctypes (olsplat_nodes/native)", -1, NULL};
PyMODINIT_FUNC PyInit__kernels(void) { return PyModule_Create(&kernels_module); }
