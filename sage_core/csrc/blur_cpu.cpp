// Separable zero-padded 'same' blur of image planes with a symmetric odd-length kernel (CPU, OpenMP).
//
// gaussian_blur(x, taps): x (P, H, W) float32 or float64, contiguous; taps (K,) of the same dtype,
// K odd and symmetric (taps[t] == taps[K - 1 - t]). Returns (P, H, W):
//   tmp[i, j] = sum_t taps[t] * x[i, j + t - K/2]       (zero outside the plane)
//   out[i, j] = sum_t taps[t] * tmp[i + t - K/2, j]
// i.e. the correlation with the outer-product window. With symmetric taps the operator is
// self-adjoint, so the same call maps an output gradient to the input gradient.
// Planes are independent: one OpenMP task per plane, each with its own scratch row buffer, so the
// result does not depend on the thread count.

#include <torch/all.h>
#include <torch/library.h>

#include <vector>

namespace {

template <typename T>
void blur_plane(const T* x, T* out, T* tmp, const T* taps, int64_t K, int64_t H, int64_t W) {
  const int64_t pad = K / 2;
  // horizontal pass into tmp
  for (int64_t i = 0; i < H; ++i) {
    const T* xr = x + i * W;
    T* tr = tmp + i * W;
    for (int64_t j = 0; j < W; ++j) tr[j] = T(0);
    for (int64_t t = 0; t < K; ++t) {
      const T w = taps[t];
      const int64_t off = t - pad;  // tr[j] += w * xr[j + off]
      const int64_t j0 = off < 0 ? -off : 0;
      const int64_t j1 = off > 0 ? W - off : W;
      for (int64_t j = j0; j < j1; ++j) tr[j] += w * xr[j + off];
    }
  }
  // vertical pass into out
  for (int64_t i = 0; i < H; ++i) {
    T* orow = out + i * W;
    for (int64_t j = 0; j < W; ++j) orow[j] = T(0);
    for (int64_t t = 0; t < K; ++t) {
      const int64_t r = i + t - pad;
      if (r < 0 || r >= H) continue;
      const T w = taps[t];
      const T* tr = tmp + r * W;
      for (int64_t j = 0; j < W; ++j) orow[j] += w * tr[j];
    }
  }
}

template <typename T>
void blur_planes(const T* x, T* out, const T* taps, int64_t P, int64_t K, int64_t H, int64_t W) {
#pragma omp parallel
  {
    std::vector<T> tmp(static_cast<size_t>(H * W));
#pragma omp for schedule(static)
    for (int64_t p = 0; p < P; ++p) blur_plane<T>(x + p * H * W, out + p * H * W, tmp.data(), taps, K, H, W);
  }
}

torch::Tensor gaussian_blur(const torch::Tensor& x, const torch::Tensor& taps) {
  TORCH_CHECK(x.device().is_cpu() && taps.device().is_cpu(), "gaussian_blur: CPU tensors expected");
  TORCH_CHECK(x.dim() == 3, "gaussian_blur: x must be (P, H, W)");
  TORCH_CHECK(taps.dim() == 1 && taps.size(0) % 2 == 1, "gaussian_blur: taps must be (K,) with K odd");
  TORCH_CHECK(x.scalar_type() == taps.scalar_type(), "gaussian_blur: x and taps must share a dtype");
  TORCH_CHECK(x.scalar_type() == torch::kFloat || x.scalar_type() == torch::kDouble, "gaussian_blur: float32 or float64");
  auto xc = x.contiguous();
  auto tc = taps.contiguous();
  auto out = torch::empty_like(xc);
  const int64_t P = xc.size(0), H = xc.size(1), W = xc.size(2), K = tc.size(0);
  if (P == 0 || H == 0 || W == 0) return out;
  AT_DISPATCH_FLOATING_TYPES(xc.scalar_type(), "gaussian_blur", [&] {
    blur_planes<scalar_t>(xc.data_ptr<scalar_t>(), out.data_ptr<scalar_t>(), tc.data_ptr<scalar_t>(), P, K, H, W);
  });
  return out;
}

}  // namespace

TORCH_LIBRARY(sage_blur_cpu, m) { m.def("gaussian_blur(Tensor x, Tensor taps) -> Tensor", &gaussian_blur); }
