// Sparse LDL^T triangular solves called directly by XLA (typed FFI), without Python.
//
// The factor (unit lower L, diagonal D and the fill-reducing permutation) is computed on
// the host by softbody.linsolve.SparseLDL and stored here under an integer key, the
// handle of softbody's factor cache. A solve looks the key up and runs
//   x = P^T L^-T D^-1 L^-1 P b
// on k right-hand sides stored row-major (n, k), inside the compiled program: no host
// callback, no GIL. Keys are looked up under a shared lock and factors are shared
// pointers, so a factor released while a solve runs stays alive until the solve ends.

#include <cstdint>
#include <cstring>
#include <memory>
#include <mutex>
#include <shared_mutex>
#include <unordered_map>
#include <vector>

#include "xla/ffi/api/ffi.h"

namespace ffi = xla::ffi;

namespace {

struct Factor {
  int64_t n = 0;
  int64_t serial = 0;
  std::vector<int64_t> colptr, rowind, perm_b, perm_x;  // L strictly lower, CSC
  std::vector<double> values, dinv;
};

std::shared_mutex table_mutex;
std::unordered_map<int64_t, std::shared_ptr<const Factor>> table;
int64_t next_serial = 1;

std::shared_ptr<const Factor> lookup(int64_t key) {
  std::shared_lock<std::shared_mutex> lock(table_mutex);
  auto it = table.find(key);
  return it == table.end() ? nullptr : it->second;
}

// y[perm_b[i]] = b[i]; L y' = y; y'' = D^-1 y'; L^T y''' = y''; x[i] = y'''[perm_x[i]].
template <int K>
void solve_fixed(const Factor& f, const double* b, double* x, double* y, int64_t k_dynamic) {
  const int64_t k = K > 0 ? K : k_dynamic;
  const int64_t n = f.n;
  const int64_t* cp = f.colptr.data();
  const int64_t* ri = f.rowind.data();
  const double* lx = f.values.data();
  for (int64_t i = 0; i < n; ++i)
    for (int64_t c = 0; c < k; ++c) y[f.perm_b[i] * k + c] = b[i * k + c];
  for (int64_t j = 0; j < n; ++j) {
    const double* yj = y + j * k;
    for (int64_t p = cp[j]; p < cp[j + 1]; ++p) {
      const double v = lx[p];
      double* yi = y + ri[p] * k;
      for (int64_t c = 0; c < k; ++c) yi[c] -= v * yj[c];
    }
  }
  for (int64_t j = 0; j < n; ++j)
    for (int64_t c = 0; c < k; ++c) y[j * k + c] *= f.dinv[j];
  for (int64_t j = n - 1; j >= 0; --j) {
    double* yj = y + j * k;
    for (int64_t p = cp[j]; p < cp[j + 1]; ++p) {
      const double v = lx[p];
      const double* yi = y + ri[p] * k;
      for (int64_t c = 0; c < k; ++c) yj[c] -= v * yi[c];
    }
  }
  for (int64_t i = 0; i < n; ++i)
    for (int64_t c = 0; c < k; ++c) x[i * k + c] = y[f.perm_x[i] * k + c];
}

// Solves size / n right-hand sides; false when size is not a multiple of n.
bool solve(const Factor& f, const double* b, double* x, int64_t size) {
  if (f.n == 0 || size % f.n != 0) return false;
  const int64_t k = size / f.n;
  std::vector<double> y(size);
  switch (k) {
    case 1: solve_fixed<1>(f, b, x, y.data(), k); break;
    case 3: solve_fixed<3>(f, b, x, y.data(), k); break;
    default: solve_fixed<0>(f, b, x, y.data(), k); break;
  }
  return true;
}

ffi::Error SolveImpl(ffi::Buffer<ffi::S64> handle, ffi::Buffer<ffi::F64> b,
                     ffi::ResultBuffer<ffi::F64> x, ffi::ResultBuffer<ffi::PRED> found) {
  if (handle.element_count() != 1 || found->element_count() != 1) {
    return ffi::Error::InvalidArgument("softbody_ldl_solve: handle and found must be scalars");
  }
  const int64_t size = static_cast<int64_t>(b.element_count());
  auto factor = lookup(handle.typed_data()[0]);
  bool ok = factor && solve(*factor, b.typed_data(), x->typed_data(), size);
  if (!ok) std::memset(x->typed_data(), 0, size * sizeof(double));
  found->typed_data()[0] = ok;
  return ffi::Error::Success();
}

}  // namespace

XLA_FFI_DEFINE_HANDLER_SYMBOL(SoftbodyLdlSolve, SolveImpl,
                              ffi::Ffi::Bind()
                                  .Arg<ffi::Buffer<ffi::S64>>()
                                  .Arg<ffi::Buffer<ffi::F64>>()
                                  .Ret<ffi::Buffer<ffi::F64>>()
                                  .Ret<ffi::Buffer<ffi::PRED>>());

extern "C" {

// Stores a factor under key (replacing any); returns its serial number (> 0), or -1.
int64_t softbody_ldl_store(int64_t key, int64_t n, const int64_t* colptr, const int64_t* rowind,
                           const double* values, const double* diag, const int64_t* perm_b,
                           const int64_t* perm_x) {
  try {
    auto f = std::make_shared<Factor>();
    f->n = n;
    f->colptr.assign(colptr, colptr + n + 1);
    f->rowind.assign(rowind, rowind + colptr[n]);
    f->values.assign(values, values + colptr[n]);
    f->perm_b.assign(perm_b, perm_b + n);
    f->perm_x.assign(perm_x, perm_x + n);
    f->dinv.resize(n);
    for (int64_t i = 0; i < n; ++i) f->dinv[i] = 1.0 / diag[i];
    std::unique_lock<std::shared_mutex> lock(table_mutex);
    f->serial = next_serial++;
    table[key] = f;
    return f->serial;
  } catch (...) {
    return -1;
  }
}

// Removes the factor stored under key if it is still the one with this serial number.
void softbody_ldl_release(int64_t key, int64_t serial) {
  std::unique_lock<std::shared_mutex> lock(table_mutex);
  auto it = table.find(key);
  if (it != table.end() && it->second->serial == serial) table.erase(it);
}

// Host-side solve of size / n right-hand sides (row-major); returns 1, or 0 if key is unknown.
int softbody_ldl_solve_host(int64_t key, const double* b, double* x, int64_t size) {
  auto factor = lookup(key);
  return factor && solve(*factor, b, x, size) ? 1 : 0;
}

// Number of factors held (for tests).
int64_t softbody_ldl_count() {
  std::shared_lock<std::shared_mutex> lock(table_mutex);
  return static_cast<int64_t>(table.size());
}

}  // extern "C"
