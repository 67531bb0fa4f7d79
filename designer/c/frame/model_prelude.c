/* cfd_model.c (cfdesign export): the model's functions, by CasADi's code generator.  They keep
 * CasADi's calling convention (arg, res, iw, w, mem), whose work and memory arguments a function may not use,
 * and the generator has no option to mark them: GCC's and Clang's warning about unused parameters is off in
 * this file only (every other warning of -std=c99 -Wall -Wextra -pedantic stays on). */
#if defined(__GNUC__)
#pragma GCC diagnostic ignored "-Wunused-parameter"
#endif
#ifndef CFD_REAL
#define CFD_REAL double
#endif
#define casadi_real CFD_REAL /* the node's numbers (cfd_node.h) */
