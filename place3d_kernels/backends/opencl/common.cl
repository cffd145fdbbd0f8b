/* Shared prelude of every program of the OpenCL backend.
 *
 * HAVE_FP64 (set by the host when the device reports cl_khr_fp64): host float64 inputs stay double on
 * the device, and the few decisions float32 cannot make exactly (near-ties in the voxel walk, edge
 * functions that are exactly zero in the watertight test, the final hit distance) are redone in double.
 * Without it, `real` is float and those decisions fall back to float32 (still within the 0.1 mm contract).
 *
 * FP_CONTRACT OFF: the watertight ray/triangle test relies on a*b - c*d rounding the same way for the two
 * triangles that share an edge; a fused multiply-add would break that symmetry.
 */
#pragma OPENCL FP_CONTRACT OFF

#ifdef HAVE_FP64
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
typedef double real;
#define REAL_MAX DBL_MAX
#else
typedef float real;
#define REAL_MAX FLT_MAX
#endif

/* Hot loops use these instead of OpenCL builtins: some CPU drivers (the PoCL wheels among them) call
 * builtins such as fmin, fabs or vload3 out of line, and a call in a traversal loop costs more than the
 * operation (and forces vector registers to be spilled around it). */
#define ALWAYS_INLINE inline __attribute__((always_inline))
#define MINF(a, b) ((a) < (b) ? (a) : (b))
#define MAXF(a, b) ((a) > (b) ? (a) : (b))
ALWAYS_INLINE float absf(float x) { return as_float(as_uint(x) & 0x7fffffffu); }
#ifdef HAVE_FP64
ALWAYS_INLINE double absd(double x) { return as_double(as_ulong(x) & 0x7fffffffffffffffUL); }
#endif
#ifdef HAVE_FP64
#define absr absd
#else
#define absr absf
#endif
