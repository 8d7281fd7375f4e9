// Sparse LDL^T factorisation and solves called directly by XLA (typed FFI), without Python.
//
// The symbolic analysis (a fill-reducing permutation P, the elimination tree and the
// column pointers of L) depends only on the sparsity pattern: softbody.linsolve.SparseLDL
// computes it once per pattern on the host (softbody_ldl_symbolic, through ctypes) and
// passes it to the compiled program as constants. Inside the program
//
//   softbody_ldl_factor  P A P^T = L D L^T, up-looking, one row of L at a time (the
//                        numeric phase of T. Davis's LDL package), from the matrix values;
//                        returns L's values and D^-1, and L's row indices, as XLA buffers;
//   softbody_ldl_solve   x = P^T L^-T D^-1 L^-1 P b with that factor, for k right-hand
//                        sides stored row-major (n, k);
//   softbody_check       fails the program with a message when a flag is set (rollout's
//                        throw=True under an outer jit/grad).
//
// None of them calls back into Python, so the programs that hold them can be written to
// JAX's persistent compilation cache. A matrix that is not positive definite, holds NaN/inf
// or has asymmetric values makes softbody_ldl_factor fail the program with an
// INVALID_ARGUMENT error naming the problem and its fix.

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <string>
#include <string_view>
#include <vector>

#include "xla/ffi/api/ffi.h"

namespace ffi = xla::ffi;

namespace {

// Elimination tree and column counts of L for P A P^T (A symmetric, CSR rows = columns;
// perm[new] = old, pinv[old] = new), from the upper triangle of the permuted matrix.
// lp (n + 1) receives L's column pointers, parent (n) the tree (-1 at the roots).
void symbolic(int64_t n, const int32_t* ap, const int32_t* ai, const int32_t* perm, const int32_t* pinv,
              int64_t* lp, int32_t* parent) {
  std::vector<int64_t> lnz(n, 0);
  std::vector<int32_t> flag(n);
  for (int64_t k = 0; k < n; ++k) {
    parent[k] = -1;
    flag[k] = static_cast<int32_t>(k);
    const int32_t kk = perm[k];
    for (int32_t p = ap[kk]; p < ap[kk + 1]; ++p) {
      int32_t i = pinv[ai[p]];
      if (i >= k) continue;
      for (; flag[i] != k; i = parent[i]) {  // walk up the tree to a node already on row k
        if (parent[i] == -1) parent[i] = static_cast<int32_t>(k);
        ++lnz[i];
        flag[i] = static_cast<int32_t>(k);
      }
    }
  }
  lp[0] = 0;
  for (int64_t k = 0; k < n; ++k) lp[k + 1] = lp[k] + lnz[k];
}

// Numeric LDL^T of P A P^T into lx (L's strictly lower values, CSC on lp), li (their row
// indices) and d. Returns n on success, else the first column k whose pivot d[k] is not
// positive (or is NaN): the matrix is not positive definite.
int64_t numeric(int64_t n, const int32_t* ap, const int32_t* ai, const double* ax, const int32_t* lp,
                const int32_t* parent, const int32_t* perm, const int32_t* pinv, int32_t* li, double* lx,
                double* d) {
  std::vector<double> y(n, 0.0);
  std::vector<int32_t> pattern(n), flag(n), lnz(n, 0);
  for (int64_t k = 0; k < n; ++k) {
    // the pattern of row k of L: the tree's reach from the nonzeros of A's column k
    int64_t top = n;
    flag[k] = static_cast<int32_t>(k);
    const int32_t kk = perm[k];
    for (int32_t p = ap[kk]; p < ap[kk + 1]; ++p) {
      int32_t i = pinv[ai[p]];
      if (i > k) continue;
      y[i] += ax[p];
      int64_t len = 0;
      for (; flag[i] != k; i = parent[i]) {
        pattern[len++] = i;
        flag[i] = static_cast<int32_t>(k);
      }
      while (len > 0) pattern[--top] = pattern[--len];
    }
    // sparse triangular solve for row k of L, and the pivot d[k]
    double dk = y[k];
    y[k] = 0.0;
    for (; top < n; ++top) {
      const int32_t i = pattern[top];
      const double yi = y[i];
      y[i] = 0.0;
      const int32_t end = lp[i] + lnz[i];
      for (int32_t p = lp[i]; p < end; ++p) y[li[p]] -= lx[p] * yi;
      const double lki = yi / d[i];
      dk -= lki * yi;
      li[end] = static_cast<int32_t>(k);
      lx[end] = lki;
      ++lnz[i];
    }
    d[k] = dk;
    if (!(dk > 0.0)) return k;
  }
  return n;
}

// L y = y, y = D^-1 y, L^T y = y in place on y (n, 3) row-major. Row j of y is held in
// locals while its column of L is applied (stores into y could alias it, so otherwise
// every update reloads it) and the L^T sums run in two independent accumulators (one is a
// serial multiply-add chain). Written out for 3 columns, the x, y, z of every PD solve;
// other column counts go 3 at a time (solve).
void substitute3(int64_t n, const int32_t* cp, const int32_t* ri, const double* lx, const double* dinv,
                 double* y) {
  for (int64_t j = 0; j < n; ++j) {
    const double a0 = y[3 * j], a1 = y[3 * j + 1], a2 = y[3 * j + 2];
    for (int32_t p = cp[j]; p < cp[j + 1]; ++p) {
      const double v = lx[p];
      double* yi = y + 3 * static_cast<int64_t>(ri[p]);
      yi[0] -= v * a0;
      yi[1] -= v * a1;
      yi[2] -= v * a2;
    }
    const double d = dinv[j];
    y[3 * j] = a0 * d;
    y[3 * j + 1] = a1 * d;
    y[3 * j + 2] = a2 * d;
  }
  for (int64_t j = n - 1; j >= 0; --j) {
    double s0 = 0.0, s1 = 0.0, s2 = 0.0, t0 = 0.0, t1 = 0.0, t2 = 0.0;
    int32_t p = cp[j];
    const int32_t end = cp[j + 1];
    for (; p + 1 < end; p += 2) {
      const double v = lx[p], w = lx[p + 1];
      const double* yi = y + 3 * static_cast<int64_t>(ri[p]);
      const double* yl = y + 3 * static_cast<int64_t>(ri[p + 1]);
      s0 += v * yi[0];
      s1 += v * yi[1];
      s2 += v * yi[2];
      t0 += w * yl[0];
      t1 += w * yl[1];
      t2 += w * yl[2];
    }
    if (p < end) {
      const double v = lx[p];
      const double* yi = y + 3 * static_cast<int64_t>(ri[p]);
      s0 += v * yi[0];
      s1 += v * yi[1];
      s2 += v * yi[2];
    }
    y[3 * j] -= s0 + t0;
    y[3 * j + 1] -= s1 + t1;
    y[3 * j + 2] -= s2 + t2;
  }
}

std::string format_double(double v) {
  char text[32];
  std::snprintf(text, sizeof text, "%.3g", v);
  return text;
}

// values = [L's strictly lower values (nnz_l), D^-1 (n)], rowind = L's row indices.
ffi::Error FactorImpl(ffi::Buffer<ffi::F64> data, ffi::Buffer<ffi::S32> indptr, ffi::Buffer<ffi::S32> cols,
                      ffi::Buffer<ffi::S32> colptr, ffi::Buffer<ffi::S32> parent, ffi::Buffer<ffi::S32> perm,
                      ffi::Buffer<ffi::S32> pinv, ffi::Buffer<ffi::PRED> asymmetric,
                      ffi::ResultBuffer<ffi::F64> values, ffi::ResultBuffer<ffi::S32> rowind,
                      std::string_view asymmetric_message, std::string_view advice) {
  const int64_t n = static_cast<int64_t>(perm.element_count());
  const int64_t nnz = static_cast<int64_t>(data.element_count());
  const int32_t* ap = indptr.typed_data();
  const int32_t* lp = colptr.typed_data();
  if (n < 1 || indptr.element_count() != static_cast<size_t>(n + 1) || colptr.element_count() != indptr.element_count() ||
      parent.element_count() != perm.element_count() || pinv.element_count() != perm.element_count() ||
      cols.element_count() != data.element_count() || ap[n] != nnz || asymmetric.element_count() != 1 ||
      rowind->element_count() != static_cast<size_t>(lp[n]) ||
      values->element_count() != static_cast<size_t>(lp[n] + n)) {
    return ffi::Error::InvalidArgument("softbody_ldl_factor: inconsistent symbolic analysis and matrix sizes");
  }
  const double* ax = data.typed_data();
  for (int64_t p = 0; p < nnz; ++p) {
    if (!std::isfinite(ax[p])) {
      return ffi::Error::InvalidArgument("SparseLDL: the matrix values contain NaN or inf (entry (" +
                                         std::to_string(std::upper_bound(ap, ap + n + 1, p) - ap - 1) + ", " +
                                         std::to_string(cols.typed_data()[p]) + ")); " + std::string(advice));
    }
  }
  if (asymmetric.typed_data()[0]) return ffi::Error::InvalidArgument(std::string(asymmetric_message));
  double* lx = values->typed_data();
  double* d = lx + lp[n];
  const int64_t k = numeric(n, ap, cols.typed_data(), ax, lp, parent.typed_data(), perm.typed_data(),
                            pinv.typed_data(), rowind->typed_data(), lx, d);
  if (k < n) {
    return ffi::Error::InvalidArgument("SparseLDL: the matrix is not positive definite (pivot " + format_double(d[k]) +
                                       " <= 0 at row " + std::to_string(perm.typed_data()[k]) + "); " +
                                       std::string(advice));
  }
  for (int64_t i = 0; i < n; ++i) d[i] = 1.0 / d[i];
  return ffi::Error::Success();
}

// x = P^T L^-T D^-1 L^-1 P b for the right-hand sides of b (n, k) row-major, three
// columns at a time (the last group padded with zeros). On the shared cantilever (2673
// columns, 166k entries) the 3 right-hand sides of a solve take 0.23-0.24 ms, against
// 0.33 ms for the same loops without the locals and the second accumulator.
ffi::Error SolveImpl(ffi::Buffer<ffi::F64> values, ffi::Buffer<ffi::S32> colptr, ffi::Buffer<ffi::S32> rowind,
                     ffi::Buffer<ffi::S32> pinv, ffi::Buffer<ffi::F64> b, ffi::ResultBuffer<ffi::F64> x) {
  const int64_t n = static_cast<int64_t>(pinv.element_count());
  const int64_t size = static_cast<int64_t>(b.element_count());
  const int32_t* cp = colptr.typed_data();
  if (n < 1 || size % n != 0 || colptr.element_count() != static_cast<size_t>(n + 1) ||
      rowind.element_count() != static_cast<size_t>(cp[n]) ||
      values.element_count() != static_cast<size_t>(cp[n] + n) || x->element_count() != b.element_count()) {
    return ffi::Error::InvalidArgument("softbody_ldl_solve: the factor does not fit the right-hand side");
  }
  const int64_t k = size / n;
  const int32_t* q = pinv.typed_data();
  const double* lx = values.typed_data();
  const double* in = b.typed_data();
  double* out = x->typed_data();
  std::vector<double> y(3 * n);
  for (int64_t c0 = 0; c0 < k; c0 += 3) {
    const int64_t m = std::min<int64_t>(3, k - c0);
    for (int64_t i = 0; i < n; ++i)
      for (int64_t c = 0; c < 3; ++c) y[3 * static_cast<int64_t>(q[i]) + c] = c < m ? in[i * k + c0 + c] : 0.0;
    substitute3(n, cp, rowind.typed_data(), lx, lx + cp[n], y.data());
    for (int64_t i = 0; i < n; ++i)
      for (int64_t c = 0; c < m; ++c) out[i * k + c0 + c] = y[3 * static_cast<int64_t>(q[i]) + c];
  }
  return ffi::Error::Success();
}

// Fails with message number branch / n_steps of messages (separated by '\x1f'), "{step}"
// replaced by branch % n_steps, when failed is set; token is 0.
ffi::Error CheckImpl(ffi::Buffer<ffi::PRED> failed, ffi::Buffer<ffi::S32> branch, ffi::ResultBuffer<ffi::S32> token,
                     std::string_view messages, int64_t n_steps) {
  token->typed_data()[0] = 0;
  if (!failed.typed_data()[0]) return ffi::Error::Success();
  const int64_t index = branch.typed_data()[0];
  const int64_t steps = std::max<int64_t>(n_steps, 1);
  int64_t variant = index / steps;
  std::string_view text = messages;
  for (; variant > 0; --variant) {
    const size_t next = text.find('\x1f');
    if (next == std::string_view::npos) break;
    text.remove_prefix(next + 1);
  }
  std::string message(text.substr(0, text.find('\x1f')));
  const std::string step = std::to_string(index % steps);
  for (size_t at = message.find("{step}"); at != std::string::npos; at = message.find("{step}", at + step.size()))
    message.replace(at, 6, step);
  return ffi::Error(ffi::ErrorCode::kFailedPrecondition, message);
}

}  // namespace

XLA_FFI_DEFINE_HANDLER_SYMBOL(SoftbodyLdlFactor, FactorImpl,
                              ffi::Ffi::Bind()
                                  .Arg<ffi::Buffer<ffi::F64>>()
                                  .Arg<ffi::Buffer<ffi::S32>>()
                                  .Arg<ffi::Buffer<ffi::S32>>()
                                  .Arg<ffi::Buffer<ffi::S32>>()
                                  .Arg<ffi::Buffer<ffi::S32>>()
                                  .Arg<ffi::Buffer<ffi::S32>>()
                                  .Arg<ffi::Buffer<ffi::S32>>()
                                  .Arg<ffi::Buffer<ffi::PRED>>()
                                  .Ret<ffi::Buffer<ffi::F64>>()
                                  .Ret<ffi::Buffer<ffi::S32>>()
                                  .Attr<std::string_view>("asymmetric")
                                  .Attr<std::string_view>("advice"));

XLA_FFI_DEFINE_HANDLER_SYMBOL(SoftbodyLdlSolve, SolveImpl,
                              ffi::Ffi::Bind()
                                  .Arg<ffi::Buffer<ffi::F64>>()
                                  .Arg<ffi::Buffer<ffi::S32>>()
                                  .Arg<ffi::Buffer<ffi::S32>>()
                                  .Arg<ffi::Buffer<ffi::S32>>()
                                  .Arg<ffi::Buffer<ffi::F64>>()
                                  .Ret<ffi::Buffer<ffi::F64>>());

XLA_FFI_DEFINE_HANDLER_SYMBOL(SoftbodyCheck, CheckImpl,
                              ffi::Ffi::Bind()
                                  .Arg<ffi::Buffer<ffi::PRED>>()
                                  .Arg<ffi::Buffer<ffi::S32>>()
                                  .Ret<ffi::Buffer<ffi::S32>>()
                                  .Attr<std::string_view>("messages")
                                  .Attr<int64_t>("n_steps"));

extern "C" {

// The symbolic analysis of P A P^T (see symbolic); returns L's number of entries.
int64_t softbody_ldl_symbolic(int64_t n, const int32_t* indptr, const int32_t* cols, const int32_t* perm,
                              const int32_t* pinv, int64_t* colptr, int32_t* parent) {
  symbolic(n, indptr, cols, perm, pinv, colptr, parent);
  return colptr[n];
}

}  // extern "C"
