// Native CPU rasterizer of 2D Gaussian surfels: the backend="cpp" path of rasterize_surfels.
//
// Same rules as the packed torch backend (sage_core/render/_packed.py, _project.py, surfels.py), see
// docs/rendering.md. Two entry points share one compositing kernel:
//   * render_forward / render_backward: one camera end to end. Per surfel: unit quaternion, rotation,
//     splat matrix M = K [a | b | p_c] with its third column rebuilt from means2d, low-pass centre,
//     normal flipped to face the camera, culling, hbb1 radius, tile rectangle and candidate pixel box;
//     the visible surfels sorted by centre depth (stable radix sort); compositing; then the image
//     outputs (colour with background, expected depth, camera and world normals, normals from depth).
//     The backward runs the same chain in reverse with exact derivatives and writes the gradients of
//     means, quaternions, scales, opacities, features, means2d and background.
//   * forward / backward: compositing only, from a per-surfel table built in torch (used when the
//     camera itself is differentiated).
// Compositing: every surfel is listed in each 16x16 tile its candidate pixel box touches, in depth
// order. A tile walks its list front to back; each surfel evaluates the pixels of its box in lanes
// of 8 along a row (ray-splat intersection, low-pass filter, alpha = min(0.99, o exp(-rho/2)), skip
// when h_z = 0, z < near or alpha < 1/255, stop before the first surfel with T (1 - alpha) < 1e-4).
// T is carried in float64; feature, alpha, depth and distortion sums are accumulated in float64 and
// rounded to the input dtype. Per-pair geometry is done in the input dtype in the packed backend's
// operation order (the build disables FMA contraction), so threshold decisions match it.
// The backward walks each tile back to front from each pixel's last contributor, recovers T by
// division, uses B <- alpha e + (1 - alpha) B for the later-surfel term of dL/dalpha and the
// closed-form distortion gradient, and writes each (tile, surfel) gradient sum to its own slot; the
// slots are added per surfel in list order afterwards, so results do not depend on the thread count.
// Tiles are processed by OpenMP threads (dynamic schedule), as many as at::get_num_threads(). On CPUs
// with AVX2 the tile loops run a build of the same code for that instruction set.

#ifndef SG_SURFELS_KERNEL_BODY

#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/empty_like.h>
#include <ATen/ops/zeros.h>
#include <ATen/ops/_to_copy.h>
#include <c10/util/Exception.h>
#include <immintrin.h>
#include <torch/library.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
#include <memory>
#include <optional>
#include <type_traits>
#include <vector>

#ifdef _OPENMP
#include <omp.h>
#endif

// Helpers on vector types are always inlined, so their vector-return ABI never matters.
#pragma GCC diagnostic ignored "-Wpsabi"
#define SG_INLINE inline __attribute__((always_inline))

namespace {

constexpr int kTile = 16;
constexpr int kTilePx = kTile * kTile;
constexpr double kAlphaMax = 0.99;
constexpr double kAlphaMin = 1.0 / 255.0;
constexpr double kTMin = 1e-4;
constexpr double kCutoff2 = 9.0;                        // the 3-sigma disc bounds the screen box
constexpr double kMinRadius = 2.1213203435596424;       // CUTOFF * FILTER_SIZE = 3 / sqrt(2)
// images smaller than this run their per-pixel loops on one thread (waking threads costs more)
constexpr int64_t kParallelPixels = 1 << 14;
constexpr int64_t kParallelSurfels = 1 << 12;
constexpr int kL = 8;  // pixels per lane chunk of the compositing kernel

int num_threads() { return std::max(1, at::get_num_threads()); }

inline void cross3(const double* a, const double* b, double* c) {
  c[0] = a[1] * b[2] - a[2] * b[1];
  c[1] = a[2] * b[0] - a[0] * b[2];
  c[2] = a[0] * b[1] - a[1] * b[0];
}

// The large temporaries of a render come from per-thread buffers reused across calls (grown on demand
// and kept for the thread's lifetime), so repeated renders do not pay for fresh pages each time.
enum WorkspaceSlot { kWsGbuf, kWsTouched, kWsTotal, kWsGstat, kWsGpay, kWsRec, kWsDepthGrad, kWsPoints, kWsCount };

template <typename T>
T* workspace(WorkspaceSlot slot, int64_t n, bool zero) {
  thread_local std::vector<char> bufs[kWsCount];
  std::vector<char>& b = bufs[slot];
  const size_t bytes = static_cast<size_t>(std::max<int64_t>(n, 1)) * sizeof(T) + 64;
  if (b.size() < bytes) {
    std::vector<char>().swap(b);
    b.resize(bytes);
  }
  T* p = reinterpret_cast<T*>((reinterpret_cast<uintptr_t>(b.data()) + 63) & ~uintptr_t(63));
  if (zero) std::memset(static_cast<void*>(p), 0, static_cast<size_t>(n) * sizeof(T));
  return p;
}

// ------------------------------------------------------------------------------------------------
// Tiles and binning.

struct Grid {
  int64_t W, H, gx, gy;
  int64_t tiles() const { return gx * gy; }
};

Grid make_grid(int64_t W, int64_t H) { return Grid{W, H, (W + kTile - 1) / kTile, (H + kTile - 1) / kTile}; }

// The pixel box of surfel r clipped to tile (tx, ty): [x0, x1) x [y0, y1); false when empty.
inline bool box_in_tile(const int64_t* boxes, int64_t r, int64_t tx, int64_t ty, int64_t& x0, int64_t& y0,
                        int64_t& x1, int64_t& y1) {
  const int64_t* b = boxes + 4 * r;
  x0 = std::max(b[0], tx * kTile);
  y0 = std::max(b[1], ty * kTile);
  x1 = std::min(b[2], tx * kTile + kTile);
  y1 = std::min(b[3], ty * kTile + kTile);
  return x1 > x0 && y1 > y0;
}

// Per-tile lists of surfel indices from candidate pixel boxes (n, 4): every surfel with a non-empty box
// is listed in each tile its box touches, in the given order (ascending indices without one).
std::vector<at::Tensor> bin_tiles_impl(const at::Tensor& boxes_t, const Grid& grid,
                                       const std::vector<int32_t>* order = nullptr) {
  const int64_t n = order != nullptr ? static_cast<int64_t>(order->size()) : boxes_t.size(0);
  const int64_t* boxes = boxes_t.data_ptr<int64_t>();
  const int64_t nt = grid.tiles();
  const auto surfel = [order](int64_t k) -> int64_t { return order != nullptr ? (*order)[k] : k; };
  at::Tensor offsets_t = at::zeros({nt + 1}, boxes_t.options().dtype(at::kLong));
  int64_t* offsets = offsets_t.data_ptr<int64_t>();
  for (int64_t k = 0; k < n; ++k) {
    const int64_t* b = boxes + 4 * surfel(k);
    if (b[2] <= b[0] || b[3] <= b[1]) continue;
    const int64_t tx0 = b[0] / kTile, ty0 = b[1] / kTile, tx1 = (b[2] - 1) / kTile + 1, ty1 = (b[3] - 1) / kTile + 1;
    for (int64_t ty = ty0; ty < ty1; ++ty)
      for (int64_t tx = tx0; tx < tx1; ++tx) offsets[ty * grid.gx + tx + 1] += 1;
  }
  for (int64_t t = 0; t < nt; ++t) offsets[t + 1] += offsets[t];
  at::Tensor lst_t = at::empty({offsets[nt]}, boxes_t.options().dtype(at::kInt));
  int32_t* lst = lst_t.data_ptr<int32_t>();
  std::vector<int64_t> fill(offsets, offsets + nt);
  for (int64_t k = 0; k < n; ++k) {
    const int64_t r = surfel(k);
    const int64_t* b = boxes + 4 * r;
    if (b[2] <= b[0] || b[3] <= b[1]) continue;
    const int64_t tx0 = b[0] / kTile, ty0 = b[1] / kTile, tx1 = (b[2] - 1) / kTile + 1, ty1 = (b[3] - 1) / kTile + 1;
    for (int64_t ty = ty0; ty < ty1; ++ty)
      for (int64_t tx = tx0; tx < tx1; ++tx) lst[fill[ty * grid.gx + tx]++] = static_cast<int32_t>(r);
  }
  return {offsets_t, lst_t};
}

// ------------------------------------------------------------------------------------------------
// Compositing kernel.
//
// Per-pixel buffers are tile-major: pixel i = row * 16 + column of tile t sits at [t][channel][i],
// each channel padded to kPad entries (zeros) for lane chunks that reach past the tile's last row.
//   aux  (tiles, 5, kPad) float64: T after the last contributor, 1/z of the first contributor, and
//        the distortion totals A, M1, M2;
//   auxi (tiles, 1, 256) int32: list index of the median contributor, or -1;
//   gstat (tiles, 4, kPad) float64: dL/dA, dL/d(sum w z), dL/dmedian, dL/ddistortion, and
//   gpay (tiles, P, kPad) in the input dtype: dL/d(payload sums) (the backward's inputs).

constexpr int kAux = 5, kAuxI = 1;
constexpr int kPad = kTilePx + kL;  // per-pixel tile buffers, padded for chunks reaching past the last row
constexpr int kSlots = 2 * kTile;  // units of a list entry: 16 rows of at most two 8-pixel chunks

template <typename S>
struct Kernel {
  const S* tab;          // (Nv, 12)
  const S* pay;          // (Nv, P)
  int64_t P;
  const int64_t* boxes;  // (Nv, 4)
  const int64_t* offsets;
  const int32_t* lst;
  S near;
  double cm;  // far near / (far - near): m(z) - m(z0) = cm (1/z0 - 1/z)
  Grid grid;
  // (L, kSlots) lane bits of the pixels each list entry contributed to, per unit (row * 2 + chunk):
  // written by the forward, read by the backward
  uint8_t* cmask;
};

struct ForwardScratch {
  // per pixel of the tile (padded by kL); the median's list index is held as float64 like the rest
  alignas(64) double T[kPad], A[kPad], Dz[kPad], M1[kPad], M2[kPad], dist[kPad], z0[kPad], med[kPad], medi[kPad];
  alignas(64) int64_t alive[kPad];  // -1 until the pixel terminates; 0 outside the image and in the padding
  std::vector<double> acc;          // (P, kPad)
  explicit ForwardScratch(int64_t P) : acc(static_cast<size_t>(P * kPad)) {}
};

struct BackwardScratch {
  alignas(64) double T[kPad], B[kPad], medi[kPad];  // per pixel of the tile (padded by kL)
  std::vector<double> acc;   // (12 + P, 8) lane sums: 12 table values, then P payload channels
  std::vector<double> accp;  // room for (P, 8) payload lane sums in the input dtype
  explicit BackwardScratch(int64_t P) : acc(static_cast<size_t>((12 + P) * kL)), accp(static_cast<size_t>(P * kL)) {
    std::fill(T, T + kPad, 0.0);
    std::fill(B, B + kPad, 0.0);
    std::fill(medi, medi + kPad, -1.0);
  }
};

// Where the backward of a tile puts the gradient sums of each list entry (12 table values, then P
// payload channels): its own slot gbuf[j] (marked in touched[j]) when tiles run in parallel, or added
// to the surfel's row of total when the tiles run in order on one thread.
struct BackwardOut {
  double* gbuf;
  unsigned char* touched;
  double* total;
};

// Lane masks for bits 0..255 (bit k set -> lane k all ones).
struct LaneMasks {
  int64_t m[256][kL];    // for float64 lanes
  int32_t m32[256][kL];  // for float32 lanes
  LaneMasks() {
    for (int b = 0; b < 256; ++b) {
      for (int k = 0; k < kL; ++k) {
        m[b][k] = (b >> k) & 1 ? -1 : 0;
        m32[b][k] = (b >> k) & 1 ? -1 : 0;
      }
    }
  }
};
const LaneMasks kLaneMasks;

// Whether a list entry's contribution masks (kSlots bytes) have any bit set.
inline bool entry_contributed(const uint8_t* m) {
  uint64_t w[kSlots / 8];
  std::memcpy(w, m, kSlots);
  uint64_t any = 0;
  for (int k = 0; k < kSlots / 8; ++k) any |= w[k];
  return any != 0;
}

// ------------------------------------------------------------------------------------------------
// The tile loops (the part of this file after "#else  // SG_SURFELS_KERNEL_BODY" below), built twice
// from the same source: for AVX2 and for SSE2, which every x86-64 CPU has. Both run the same
// operations in the same order, so they give the same results; AVX2 is used when the CPU has it.

}  // namespace

#define SG_SURFELS_KERNEL_BODY
#pragma GCC push_options
#pragma GCC target("avx2")
#define SG_SURFELS_ISA IsaAvx2
#define SG_SURFELS_AVX2 1
namespace {
namespace avx2 {
#include __FILE__
}  // namespace avx2
}  // namespace
#undef SG_SURFELS_ISA
#undef SG_SURFELS_AVX2
#pragma GCC pop_options
#define SG_SURFELS_ISA IsaSse2
#define SG_SURFELS_AVX2 0
namespace {
namespace sse2 {
#include __FILE__
}  // namespace sse2
}  // namespace
#undef SG_SURFELS_ISA
#undef SG_SURFELS_AVX2
#undef SG_SURFELS_KERNEL_BODY

namespace {

bool& avx2_enabled() {
  static bool on = __builtin_cpu_supports("avx2");
  return on;
}

template <typename S, typename Sink>
int64_t run_forward(const Kernel<S>& in, double* aux, int32_t* auxi, Sink& sink) {
  const int64_t nt = in.grid.tiles();
  const bool avx2 = avx2_enabled();
  const int nth = num_threads();
  std::vector<int64_t> pairs(static_cast<size_t>(nt), 0);
#pragma omp parallel num_threads(nth) if (nt > 1 && nth > 1)
  {
    auto scratch = std::make_unique<ForwardScratch>(in.P);
#pragma omp for schedule(dynamic, 1)
    for (int64_t t = 0; t < nt; ++t) {
      if (avx2)
        pairs[t] = avx2::forward_tile<S, Sink>(t, in, *scratch, aux, auxi, sink);
      else
        pairs[t] = sse2::forward_tile<S, Sink>(t, in, *scratch, aux, auxi, sink);
    }
  }
  int64_t total = 0;
  for (const int64_t n : pairs) total += n;
  return total;  // composited (surfel, pixel) pairs
}

// Fills per-pixel gradients in the tile-major layouts gstat (tiles, 4, kPad) float64 and gpay (tiles, P,
// kPad): fill(y, x, st, pay) writes channel c of image pixel (y, x) to st[c * kPad] and pay[c * kPad];
// pixels outside the image and the padding are zero.
template <typename S, typename Fill>
void fill_tile_major(const Grid& grid, double* gstat, S* gpay, int64_t P, const Fill& fill) {
  for (int64_t t = 0; t < grid.tiles(); ++t) {
    const int64_t tx = t % grid.gx, ty = t / grid.gx;
    double* st = gstat + t * 4 * kPad;
    S* pay = gpay + t * P * kPad;
    for (int c = 0; c < 4; ++c) std::fill(st + c * kPad + kTilePx, st + (c + 1) * kPad, 0.0);
    for (int64_t c = 0; c < P; ++c) std::fill(pay + c * kPad + kTilePx, pay + (c + 1) * kPad, S(0));
    for (int row = 0; row < kTile; ++row) {
      const int64_t y = ty * kTile + row;
      for (int col = 0; col < kTile; ++col) {
        const int64_t x = tx * kTile + col, i = row * kTile + col;
        if (y < grid.H && x < grid.W) {
          fill(y, x, st + i, pay + i);
        } else {
          for (int c = 0; c < 4; ++c) st[c * kPad + i] = 0.0;
          for (int64_t c = 0; c < P; ++c) pay[c * kPad + i] = S(0);
        }
      }
    }
  }
}

// Backward of every tile; the per-entry sums are added per surfel in list order. Returns the float64
// gradients of the table rows and payload channels, (n, 12 + P) for a table of n rows (zero rows for
// surfels in no list).
template <typename S>
const double* run_backward(const Kernel<S>& in, int64_t n, const double* aux, const int32_t* auxi,
                           const double* gstat, const S* gpay) {
  const int64_t nt = in.grid.tiles(), G = 12 + in.P, L = in.offsets[nt];
  const bool avx2 = avx2_enabled();
  const int nth = num_threads();
  double* total = workspace<double>(kWsTotal, n * G, true);
  if (nt <= 1 || nth <= 1) {
    // one thread: the tiles in order add straight into the totals, the same sums in the same order
    BackwardOut out{nullptr, nullptr, total};
    BackwardScratch scratch(in.P);
    for (int64_t t = 0; t < nt; ++t) {
      if (avx2)
        avx2::backward_tile<S>(t, in, aux, auxi, gstat, gpay, scratch, out);
      else
        sse2::backward_tile<S>(t, in, aux, auxi, gstat, gpay, scratch, out);
    }
    return total;
  }
  BackwardOut out{workspace<double>(kWsGbuf, L * G, false), workspace<unsigned char>(kWsTouched, L, true), nullptr};
#pragma omp parallel num_threads(nth)
  {
    auto scratch = std::make_unique<BackwardScratch>(in.P);
#pragma omp for schedule(dynamic, 1)
    for (int64_t t = 0; t < nt; ++t) {
      if (avx2)
        avx2::backward_tile<S>(t, in, aux, auxi, gstat, gpay, *scratch, out);
      else
        sse2::backward_tile<S>(t, in, aux, auxi, gstat, gpay, *scratch, out);
    }
  }
  for (int64_t j = 0; j < L; ++j) {
    if (!out.touched[j]) continue;
    double* dst = total + G * in.lst[j];
    const double* src = out.gbuf + G * j;
    for (int64_t c = 0; c < G; ++c) dst[c] += src[c];
  }
  return total;
}

// ------------------------------------------------------------------------------------------------
// Compositing from a table built in torch: forward / backward.

template <typename S>
struct TableSink {  // pay_out (HW, P) payload sums; stats (HW, 4) = A, sum w z, median, distortion
  S* pay_out;
  S* stats;
  int64_t P;
  void store(int64_t p, int i, const ForwardScratch& s) {
    for (int64_t c = 0; c < P; ++c) pay_out[p * P + c] = static_cast<S>(s.acc[c * kPad + i]);
    S* st = stats + 4 * p;
    st[0] = static_cast<S>(s.A[i]);
    st[1] = static_cast<S>(s.Dz[i]);
    st[2] = static_cast<S>(s.med[i]);
    st[3] = static_cast<S>(s.dist[i]);
  }
};

void check_table_inputs(const at::Tensor& table, const at::Tensor& payload, const at::Tensor& boxes) {
  TORCH_CHECK(table.device().is_cpu() && payload.device().is_cpu() && boxes.device().is_cpu(),
              "surfels_cpu: tensors must be on the CPU");
  TORCH_CHECK(table.dim() == 2 && table.size(1) == 12 && table.is_contiguous(),
              "surfels_cpu: table must be a contiguous (Nv, 12) tensor");
  TORCH_CHECK(payload.dim() == 2 && payload.size(0) == table.size(0) && payload.is_contiguous(),
              "surfels_cpu: payload must be a contiguous (Nv, P) tensor");
  TORCH_CHECK(payload.scalar_type() == table.scalar_type(), "surfels_cpu: table and payload dtypes differ");
  TORCH_CHECK(table.scalar_type() == at::kFloat || table.scalar_type() == at::kDouble,
              "surfels_cpu: dtype must be float32 or float64");
  TORCH_CHECK(boxes.dim() == 2 && boxes.size(0) == table.size(0) && boxes.size(1) == 4 && boxes.is_contiguous() &&
                  boxes.scalar_type() == at::kLong,
              "surfels_cpu: boxes must be a contiguous (Nv, 4) int64 tensor");
}

template <typename S>
Kernel<S> make_kernel(const at::Tensor& table, const at::Tensor& payload, const at::Tensor& boxes,
                      const at::Tensor& offsets, const at::Tensor& lst, const at::Tensor& cmask, const Grid& grid,
                      double near, double far) {
  return Kernel<S>{table.data_ptr<S>(),       payload.data_ptr<S>(),       payload.size(1),
                   boxes.data_ptr<int64_t>(), offsets.data_ptr<int64_t>(), lst.data_ptr<int32_t>(),
                   static_cast<S>(near),      far * near / (far - near),   grid,
                   cmask.data_ptr<uint8_t>()};
}

// The contribution masks of a tile list (L, kSlots) uint8, set by the forward (each tile clears its own).
at::Tensor new_cmask(const at::Tensor& lst) { return at::empty({lst.size(0), kSlots}, lst.options().dtype(at::kByte)); }

// table (Nv, 12), payload (Nv, P), boxes (Nv, 4) int64 -> [pay_out (HW, P), stats (HW, 4), aux, auxi,
// offsets (tiles + 1) i64, lst (L,) i32, cmask (L, kSlots) u8, composited pairs (0-dim i64)].
std::vector<at::Tensor> composite_forward(const at::Tensor& table, const at::Tensor& payload, const at::Tensor& boxes,
                                          int64_t width, int64_t height, double near, double far) {
  check_table_inputs(table, payload, boxes);
  TORCH_CHECK(width > 0 && height > 0, "surfels_cpu: image size must be positive");
  const Grid grid = make_grid(width, height);
  const int64_t HW = width * height, P = payload.size(1), nt = grid.tiles();
  auto bins = bin_tiles_impl(boxes, grid);
  at::Tensor pay_out = at::empty({HW, P}, table.options());
  at::Tensor stats = at::empty({HW, 4}, table.options());
  at::Tensor aux = at::empty({nt, kAux, kPad}, table.options().dtype(at::kDouble));
  at::Tensor auxi = at::empty({nt, kAuxI, kTilePx}, table.options().dtype(at::kInt));
  at::Tensor cmask = new_cmask(bins[1]);
  int64_t n_pairs = 0;
  AT_DISPATCH_FLOATING_TYPES(table.scalar_type(), "surfels_cpu_forward", [&] {
    const Kernel<scalar_t> in = make_kernel<scalar_t>(table, payload, boxes, bins[0], bins[1], cmask, grid, near, far);
    TableSink<scalar_t> sink{pay_out.data_ptr<scalar_t>(), stats.data_ptr<scalar_t>(), P};
    n_pairs = run_forward<scalar_t>(in, aux.data_ptr<double>(), auxi.data_ptr<int32_t>(), sink);
  });
  at::Tensor pairs = at::empty({}, boxes.options().dtype(at::kLong));
  pairs.fill_(n_pairs);
  return {pay_out, stats, aux, auxi, bins[0], bins[1], cmask, pairs};
}

void check_aux(const at::Tensor& aux, const at::Tensor& auxi, const at::Tensor& offsets, const at::Tensor& lst,
               const at::Tensor& cmask, const Grid& grid) {
  const int64_t nt = grid.tiles();
  TORCH_CHECK(aux.sizes() == at::IntArrayRef({nt, kAux, kPad}) && aux.scalar_type() == at::kDouble &&
                  aux.is_contiguous() && auxi.sizes() == at::IntArrayRef({nt, kAuxI, kTilePx}) &&
                  auxi.scalar_type() == at::kInt && auxi.is_contiguous(),
              "surfels_cpu: aux buffers do not match the image size");
  TORCH_CHECK(offsets.numel() == nt + 1 && offsets.scalar_type() == at::kLong && lst.scalar_type() == at::kInt &&
                  offsets.is_contiguous() && lst.is_contiguous(),
              "surfels_cpu: tile lists do not match the image size");
  TORCH_CHECK(cmask.sizes() == at::IntArrayRef({lst.size(0), kSlots}) && cmask.scalar_type() == at::kByte &&
                  cmask.is_contiguous(),
              "surfels_cpu: contribution masks do not match the tile lists");
}

// Gradients of the table (Nv, 12) and payload (Nv, P) from the output gradients g_pay (HW, P) and
// g_stats (HW, 4) (A, sum w z, median, distortion).
std::vector<at::Tensor> composite_backward(const at::Tensor& table, const at::Tensor& payload, const at::Tensor& boxes,
                                           const at::Tensor& offsets, const at::Tensor& lst, const at::Tensor& aux,
                                           const at::Tensor& auxi, const at::Tensor& cmask, const at::Tensor& g_pay,
                                           const at::Tensor& g_stats,
                                           int64_t width, int64_t height, double near, double far) {
  check_table_inputs(table, payload, boxes);
  const int64_t HW = width * height, P = payload.size(1), nv = table.size(0);
  TORCH_CHECK(g_pay.sizes() == at::IntArrayRef({HW, P}) && g_pay.is_contiguous() &&
                  g_pay.scalar_type() == table.scalar_type(),
              "surfels_cpu: g_pay must be a contiguous (HW, P) tensor of the table's dtype");
  TORCH_CHECK(g_stats.sizes() == at::IntArrayRef({HW, 4}) && g_stats.is_contiguous() &&
                  g_stats.scalar_type() == table.scalar_type(),
              "surfels_cpu: g_stats must be a contiguous (HW, 4) tensor of the table's dtype");
  const Grid grid = make_grid(width, height);
  check_aux(aux, auxi, offsets, lst, cmask, grid);
  at::Tensor gtab = at::empty_like(table);
  at::Tensor gpay = at::empty_like(payload);
  AT_DISPATCH_FLOATING_TYPES(table.scalar_type(), "surfels_cpu_backward", [&] {
    using S = scalar_t;
    double* gstat = workspace<double>(kWsGstat, grid.tiles() * 4 * kPad, false);
    S* gpix = workspace<S>(kWsGpay, grid.tiles() * P * kPad, false);
    const S* gp = g_pay.data_ptr<S>();
    const S* gs = g_stats.data_ptr<S>();
    fill_tile_major<S>(grid, gstat, gpix, P, [gp, gs, P, width](int64_t y, int64_t x, double* st, S* pay) {
      const int64_t p = y * width + x;
      for (int64_t c = 0; c < P; ++c) pay[c * kPad] = gp[p * P + c];
      for (int64_t c = 0; c < 4; ++c) st[c * kPad] = gs[4 * p + c];
    });
    const Kernel<S> in = make_kernel<S>(table, payload, boxes, offsets, lst, cmask, grid, near, far);
    const double* total = run_backward<S>(in, nv, aux.data_ptr<double>(), auxi.data_ptr<int32_t>(), gstat, gpix);
    S* gt = gtab.data_ptr<S>();
    S* gq = gpay.data_ptr<S>();
    const int64_t G = 12 + P;
    for (int64_t r = 0; r < nv; ++r) {
      for (int64_t c = 0; c < 12; ++c) gt[12 * r + c] = static_cast<S>(total[G * r + c]);
      for (int64_t c = 0; c < P; ++c) gq[P * r + c] = static_cast<S>(total[G * r + 12 + c]);
    }
  });
  return {gtab, gpay};
}

std::vector<at::Tensor> bin_tiles(const at::Tensor& boxes, int64_t width, int64_t height) {
  TORCH_CHECK(boxes.dim() == 2 && boxes.size(1) == 4 && boxes.is_contiguous() && boxes.scalar_type() == at::kLong &&
                  boxes.device().is_cpu(),
              "surfels_cpu: boxes must be a contiguous (Nv, 4) int64 CPU tensor");
  return bin_tiles_impl(boxes, make_grid(width, height));
}

// ------------------------------------------------------------------------------------------------
// Normals from depth (surfels.depth_to_normal): P(y, x) = z(y, x) K^-1 (x + 0.5, y + 0.5, 1),
// c = (P(y+1, x) - P(y-1, x)) x (P(y, x+1) - P(y, x-1)), n = c / max(|c|, 1e-12), 1-px border 0.
// Computed in float64.

struct DepthNormalGeom {
  int64_t H, W;
  double ki[9];
  template <typename Z>
  void point(const Z* z, int64_t y, int64_t x, double* out) const {
    const double px = static_cast<double>(x) + 0.5, py = static_cast<double>(y) + 0.5;
    const double d = static_cast<double>(z[y * W + x]);
    for (int k = 0; k < 3; ++k) out[k] = d * (ki[3 * k] * px + ki[3 * k + 1] * py + ki[3 * k + 2]);
  }
  // every back-projected point P (H, W, 3), into a per-thread buffer
  template <typename Z>
  const double* points(const Z* z) const {
    double* P = workspace<double>(kWsPoints, 3 * H * W, false);
    for (int64_t y = 0; y < H; ++y)
      for (int64_t x = 0; x < W; ++x) point(z, y, x, P + 3 * (y * W + x));
    return P;
  }
  // the two difference vectors a = P(y+1,x) - P(y-1,x), b = P(y,x+1) - P(y,x-1) of an interior pixel
  void diffs(const double* P, int64_t y, int64_t x, double* a, double* b) const {
    const double *up = P + 3 * ((y - 1) * W + x), *down = P + 3 * ((y + 1) * W + x);
    const double *left = P + 3 * (y * W + x - 1), *right = P + 3 * (y * W + x + 1);
    for (int k = 0; k < 3; ++k) {
      a[k] = down[k] - up[k];
      b[k] = right[k] - left[k];
    }
  }
};

// z (H, W) -> the normal of every pixel, passed to put(p, n[3]) (0 on the border).
template <typename Z, typename Put>
void dn_forward(const DepthNormalGeom& geo, const Z* z, const Put& put) {
  const int64_t H = geo.H, W = geo.W;
  const double zero[3] = {0.0, 0.0, 0.0};
  const double* P = geo.points(z);
#pragma omp parallel for schedule(static) num_threads(num_threads()) if (H * W >= kParallelPixels && num_threads() > 1)
  for (int64_t y = 0; y < H; ++y) {
    for (int64_t x = 0; x < W; ++x) {
      if (y == 0 || x == 0 || y == H - 1 || x == W - 1) {
        put(y * W + x, zero);
        continue;
      }
      double a[3], b[3], c[3], n[3];
      geo.diffs(P, y, x, a, b);
      cross3(a, b, c);
      const double len = std::max(std::sqrt(c[0] * c[0] + c[1] * c[1] + c[2] * c[2]), 1e-12);
      for (int k = 0; k < 3; ++k) n[k] = c[k] / len;
      put(y * W + x, n);
    }
  }
}

// Gradient of dn_forward: grad_at(y, x, g[3]) gives dL/dn of interior pixel (y, x); writes dL/dz to gz (H, W).
// Rows are processed in order with the difference-vector gradients of three rows kept at a time.
template <typename Z, typename GradAt>
void dn_backward(const DepthNormalGeom& geo, const Z* z, const GradAt& grad_at, double* gz) {
  const int64_t H = geo.H, W = geo.W;
  const double* P = geo.points(z);
  // dL/da and dL/db (a vertical, b horizontal difference vector) of rows y - 1, y, y + 1, ring-indexed by y % 3
  std::vector<double> ring_a(static_cast<size_t>(9 * W)), ring_b(static_cast<size_t>(9 * W));
  const auto fill_row = [&](int64_t y) {
    double* ga = ring_a.data() + (y % 3) * 3 * W;
    double* gb = ring_b.data() + (y % 3) * 3 * W;
    std::fill(ga, ga + 3 * W, 0.0);
    std::fill(gb, gb + 3 * W, 0.0);
    if (y <= 0 || y >= H - 1) return;
    for (int64_t x = 1; x < W - 1; ++x) {
      double a[3], b[3], c[3], gn[3], gc[3];
      geo.diffs(P, y, x, a, b);
      cross3(a, b, c);
      grad_at(y, x, gn);
      const double norm = std::sqrt(c[0] * c[0] + c[1] * c[1] + c[2] * c[2]);
      if (norm > 1e-12) {  // n = c / |c|
        const double dot = (c[0] * gn[0] + c[1] * gn[1] + c[2] * gn[2]) / (norm * norm);
        for (int k = 0; k < 3; ++k) gc[k] = (gn[k] - c[k] * dot) / norm;
      } else {  // n = c / 1e-12
        for (int k = 0; k < 3; ++k) gc[k] = gn[k] / 1e-12;
      }
      cross3(b, gc, ga + 3 * x);  // c = a x b: dL/da = b x gc, dL/db = gc x a
      cross3(gc, a, gb + 3 * x);
    }
  };
  if (H > 0) fill_row(0);
  if (H > 1) fill_row(1);
  for (int64_t y = 0; y < H; ++y) {
    if (y + 1 < H && y >= 1) fill_row(y + 1);
    const double* up = ring_a.data() + ((y + 2) % 3) * 3 * W;    // row y - 1
    const double* down = ring_a.data() + ((y + 1) % 3) * 3 * W;  // row y + 1
    const double* gb = ring_b.data() + (y % 3) * 3 * W;
    for (int64_t x = 0; x < W; ++x) {
      // P(y, x) enters a of (y-1, x) with +, a of (y+1, x) with -, b of (y, x-1) with +, b of (y, x+1) with -
      double gp[3] = {0.0, 0.0, 0.0};
      for (int k = 0; k < 3; ++k) {
        if (y >= 1) gp[k] += up[3 * x + k];
        if (y + 1 < H) gp[k] -= down[3 * x + k];
        if (x >= 1) gp[k] += gb[3 * (x - 1) + k];
        if (x + 1 < W) gp[k] -= gb[3 * (x + 1) + k];
      }
      const double px = static_cast<double>(x) + 0.5, py = static_cast<double>(y) + 0.5;
      double s = 0.0;
      for (int k = 0; k < 3; ++k) s += gp[k] * (geo.ki[3 * k] * px + geo.ki[3 * k + 1] * py + geo.ki[3 * k + 2]);
      gz[y * W + x] = s;
    }
  }
}

DepthNormalGeom depth_normal_geom(const at::Tensor& depth, const at::Tensor& kinv) {
  TORCH_CHECK(depth.dim() == 2 && depth.device().is_cpu(), "surfels_cpu: depth must be a (H, W) CPU tensor");
  TORCH_CHECK(kinv.sizes() == at::IntArrayRef({3, 3}) && kinv.scalar_type() == at::kDouble && kinv.is_contiguous(),
              "surfels_cpu: kinv must be a contiguous (3, 3) float64 tensor");
  DepthNormalGeom geo{depth.size(0), depth.size(1), {}};
  const double* k = kinv.data_ptr<double>();
  std::copy(k, k + 9, geo.ki);
  return geo;
}

// depth (H, W) float32/float64, kinv (3, 3) float64 -> normal (H, W, 3) in depth's dtype.
at::Tensor depth_normal_forward(const at::Tensor& depth_in, const at::Tensor& kinv) {
  const DepthNormalGeom geo = depth_normal_geom(depth_in, kinv);
  const at::Tensor z64 = depth_in.to(at::kDouble).contiguous();
  at::Tensor out = at::empty({geo.H, geo.W, 3}, z64.options());
  double* n = out.data_ptr<double>();
  dn_forward(geo, z64.data_ptr<double>(), [n](int64_t p, const double* v) {
    for (int k = 0; k < 3; ++k) n[3 * p + k] = v[k];
  });
  return out.to(depth_in.scalar_type());
}

// Gradient of depth_normal_forward: grad (H, W, 3) -> d depth (H, W).
at::Tensor depth_normal_backward(const at::Tensor& depth_in, const at::Tensor& kinv, const at::Tensor& grad_in) {
  const DepthNormalGeom geo = depth_normal_geom(depth_in, kinv);
  TORCH_CHECK(grad_in.sizes() == at::IntArrayRef({geo.H, geo.W, 3}), "surfels_cpu: grad must be (H, W, 3)");
  const at::Tensor z64 = depth_in.to(at::kDouble).contiguous();
  const at::Tensor g64 = grad_in.to(at::kDouble).contiguous();
  at::Tensor out = at::empty({geo.H, geo.W}, z64.options());
  const double* g = g64.data_ptr<double>();
  const int64_t W = geo.W;
  dn_backward(geo, z64.data_ptr<double>(), [g, W](int64_t y, int64_t x, double* v) {
    for (int k = 0; k < 3; ++k) v[k] = g[3 * (y * W + x) + k];
  }, out.data_ptr<double>());
  return out.to(depth_in.scalar_type());
}

int64_t max_threads() { return num_threads(); }

bool use_avx2(bool on) {
  const bool before = avx2_enabled();
  avx2_enabled() = on && __builtin_cpu_supports("avx2");
  return before;
}

// ------------------------------------------------------------------------------------------------
// One camera end to end: projection (_project.py), depth order, table, compositing and image outputs.

template <typename S>
struct Camera {
  S K[9], R[9], t[3];  // intrinsics; world-to-camera rotation (row-major) and translation
  double Kd[9], Rd[9], Kinv[9];
  Grid grid;
  S near;
};

void invert3(const double* m, double* out) {
  const double c00 = m[4] * m[8] - m[5] * m[7], c01 = m[5] * m[6] - m[3] * m[8], c02 = m[3] * m[7] - m[4] * m[6];
  const double det = m[0] * c00 + m[1] * c01 + m[2] * c02;
  out[0] = c00 / det;
  out[1] = (m[2] * m[7] - m[1] * m[8]) / det;
  out[2] = (m[1] * m[5] - m[2] * m[4]) / det;
  out[3] = c01 / det;
  out[4] = (m[0] * m[8] - m[2] * m[6]) / det;
  out[5] = (m[2] * m[3] - m[0] * m[5]) / det;
  out[6] = c02 / det;
  out[7] = (m[1] * m[6] - m[0] * m[7]) / det;
  out[8] = (m[0] * m[4] - m[1] * m[3]) / det;
}

template <typename S>
Camera<S> make_camera(const S* k, const S* m, int64_t W, int64_t H, double near) {
  Camera<S> c;
  for (int i = 0; i < 9; ++i) {
    c.K[i] = k[i];
    c.Kd[i] = k[i];
  }
  for (int i = 0; i < 3; ++i) {
    for (int j = 0; j < 3; ++j) {
      c.R[3 * i + j] = m[4 * i + j];
      c.Rd[3 * i + j] = m[4 * i + j];
    }
    c.t[i] = m[4 * i + 3];
  }
  invert3(c.Kd, c.Kinv);
  c.grid = make_grid(W, H);
  c.near = static_cast<S>(near);
  return c;
}

// 3-vector products in the dtype S, summed left to right.
template <typename S>
inline S dot3(const S* a, const S* b) {
  return (a[0] * b[0] + a[1] * b[1]) + a[2] * b[2];
}

// The projection of one surfel (docs/rendering.md §1.2, 1.7), in the input dtype as in _project.py.
template <typename S>
struct SurfelProj {
  S q[4];      // unit quaternion (w, x, y, z)
  S norm;      // |q| before the 1e-12 clamp
  S R[9];      // rotation, row-major: columns t_u, t_v, t_w
  S a[3], b[3], pc[3], n[3];
  S zs;        // centre depth, or 1 when |depth| <= 1e-12
  bool zok;
  S Tu[3], Tv[3], Tw[3];
  S d, cx, cy, sign;
  bool cos_ok;
};

template <typename S>
void project_surfel(const S* mean, const S* quat, const S* scale, const S* m2, const Camera<S>& cam,
                    SurfelProj<S>& p) {
  const S q0 = quat[0], q1 = quat[1], q2 = quat[2], q3 = quat[3];
  p.norm = std::sqrt(((q0 * q0 + q1 * q1) + q2 * q2) + q3 * q3);
  const S den = std::max(p.norm, static_cast<S>(1e-12));
  const S w = q0 / den, x = q1 / den, y = q2 / den, z = q3 / den;
  p.q[0] = w;
  p.q[1] = x;
  p.q[2] = y;
  p.q[3] = z;
  S* R = p.R;
  R[0] = S(1) - S(2) * (y * y + z * z);
  R[1] = S(2) * (x * y - w * z);
  R[2] = S(2) * (x * z + w * y);
  R[3] = S(2) * (x * y + w * z);
  R[4] = S(1) - S(2) * (x * x + z * z);
  R[5] = S(2) * (y * z - w * x);
  R[6] = S(2) * (x * z - w * y);
  R[7] = S(2) * (y * z + w * x);
  R[8] = S(1) - S(2) * (x * x + y * y);
  const S ap[3] = {R[0] * scale[0], R[3] * scale[0], R[6] * scale[0]};
  const S bp[3] = {R[1] * scale[1], R[4] * scale[1], R[7] * scale[1]};
  const S tw[3] = {R[2], R[5], R[8]};
  for (int i = 0; i < 3; ++i) {
    const S* row = cam.R + 3 * i;
    p.a[i] = dot3(row, ap);
    p.b[i] = dot3(row, bp);
    p.n[i] = dot3(row, tw);
    p.pc[i] = dot3(row, mean) + cam.t[i];
  }
  S M0[9];
  for (int i = 0; i < 3; ++i) {
    const S* k = cam.K + 3 * i;
    M0[3 * i] = dot3(k, p.a);
    M0[3 * i + 1] = dot3(k, p.b);
    M0[3 * i + 2] = dot3(k, p.pc);
  }
  const S zc = p.pc[2];
  p.zok = std::fabs(zc) > static_cast<S>(1e-12);
  p.zs = p.zok ? zc : S(1);
  p.Tu[0] = M0[0];
  p.Tu[1] = M0[1];
  p.Tu[2] = m2[0] * p.zs;
  p.Tv[0] = M0[3];
  p.Tv[1] = M0[4];
  p.Tv[2] = m2[1] * p.zs;
  p.Tw[0] = M0[6];
  p.Tw[1] = M0[7];
  p.Tw[2] = M0[8];
  const S c2 = static_cast<S>(kCutoff2);
  const S *Tu = p.Tu, *Tv = p.Tv, *Tw = p.Tw;
  p.d = c2 * (Tw[0] * Tw[0] + Tw[1] * Tw[1]) - Tw[2] * Tw[2];
  const S ds = p.d < 0 ? p.d : S(-1);
  p.cx = (c2 * (Tu[0] * Tw[0] + Tu[1] * Tw[1]) - Tu[2] * Tw[2]) / ds;
  p.cy = (c2 * (Tv[0] * Tw[0] + Tv[1] * Tw[1]) - Tv[2] * Tw[2]) / ds;
  const S cosv = -dot3(p.pc, p.n);
  p.sign = cosv > 0 ? S(1) : S(-1);
  p.cos_ok = cosv != 0;
}

// Culling, hbb1 radius and tile rectangle (tx0, ty0, tx1, ty1) of a projected surfel.
template <typename S>
bool surfel_rect(const SurfelProj<S>& p, const Camera<S>& cam, int64_t& radius, int64_t* rect) {
  const S c2 = static_cast<S>(kCutoff2);
  const S *Tu = p.Tu, *Tv = p.Tv;
  const S ds = p.d < 0 ? p.d : S(-1);
  const S uu = (c2 * (Tu[0] * Tu[0] + Tu[1] * Tu[1]) - Tu[2] * Tu[2]) / ds;
  const S vv = (c2 * (Tv[0] * Tv[0] + Tv[1] * Tv[1]) - Tv[2] * Tv[2]) / ds;
  const S hx = std::sqrt(std::max(p.cx * p.cx - uu, static_cast<S>(1e-4)));
  const S hy = std::sqrt(std::max(p.cy * p.cy - vv, static_cast<S>(1e-4)));
  const bool ok = p.pc[2] > cam.near && p.d < 0 && p.cos_ok && std::isfinite(hx) && std::isfinite(hy);
  radius = 0;
  for (int k = 0; k < 4; ++k) rect[k] = 0;
  if (!ok) return false;
  const S r = std::ceil(std::max(std::max(hx, hy), static_cast<S>(kMinRadius)));
  const double big = 1e9;
  const double px = std::min(std::max(static_cast<double>(p.cx - S(0.5)), -big), big);
  const double py = std::min(std::max(static_cast<double>(p.cy - S(0.5)), -big), big);
  const double r64 = std::min(std::max(static_cast<double>(r), 0.0), big);
  const double gx = static_cast<double>(cam.grid.gx), gy = static_cast<double>(cam.grid.gy);
  const auto tile_of = [](double v, double hi) {
    return static_cast<int64_t>(std::min(std::max(std::floor(v / kTile), 0.0), hi));
  };
  const int64_t tx0 = tile_of(px - r64, gx), ty0 = tile_of(py - r64, gy);
  const int64_t tx1 = tile_of(px + r64 + (kTile - 1), gx), ty1 = tile_of(py + r64 + (kTile - 1), gy);
  if ((tx1 - tx0) * (ty1 - ty0) <= 0) return false;
  radius = static_cast<int64_t>(r64);
  rect[0] = tx0;
  rect[1] = ty0;
  rect[2] = tx1;
  rect[3] = ty1;
  return true;
}

inline double nan_min(double a, double b) { return (a != a || b != b) ? std::numeric_limits<double>::quiet_NaN() : std::min(a, b); }
inline double nan_max(double a, double b) { return (a != a || b != b) ? std::numeric_limits<double>::quiet_NaN() : std::max(a, b); }

// candidate_pixel_boxes of _project.py for one surfel (float64): the pixels of its tiles where alpha can
// reach 1/255, widened by one pixel; (x0, y0, x1, y1), max exclusive, x1 = x0 and y1 = y0 when empty.
template <typename S>
void candidate_box(const S* Tus, const S* Tvs, const S* Tws, S cxs, S cys, S os, const int64_t* rect, int64_t W,
                   int64_t H, int64_t* box) {
  const double Tu[3] = {Tus[0], Tus[1], Tus[2]}, Tv[3] = {Tvs[0], Tvs[1], Tvs[2]}, Tw[3] = {Tws[0], Tws[1], Tws[2]};
  const double o = os;
  const double B = std::max(2.0 * std::log(std::max(255.0 * o, 1e-30)), 0.0);
  const double d = B * (Tw[0] * Tw[0] + Tw[1] * Tw[1]) - Tw[2] * Tw[2];
  bool bounded = d < 0;
  const double ds = bounded ? d : -1.0;
  const double ex = (B * (Tu[0] * Tw[0] + Tu[1] * Tw[1]) - Tu[2] * Tw[2]) / ds;
  const double ey = (B * (Tv[0] * Tw[0] + Tv[1] * Tw[1]) - Tv[2] * Tw[2]) / ds;
  const double uu = (B * (Tu[0] * Tu[0] + Tu[1] * Tu[1]) - Tu[2] * Tu[2]) / ds;
  const double vv = (B * (Tv[0] * Tv[0] + Tv[1] * Tv[1]) - Tv[2] * Tv[2]) / ds;
  const double hx = std::sqrt(std::max(ex * ex - uu, 0.0));
  const double hy = std::sqrt(std::max(ey * ey - vv, 0.0));
  const double r2 = std::sqrt(B / 2.0);
  const double cx = cxs, cy = cys;
  const double lo_x = nan_min(ex - hx, cx - r2), hi_x = nan_max(ex + hx, cx + r2);
  const double lo_y = nan_min(ey - hy, cy - r2), hi_y = nan_max(ey + hy, cy + r2);
  bounded = bounded && std::isfinite(lo_x) && std::isfinite(hi_x) && std::isfinite(lo_y) && std::isfinite(hi_y);
  const double big = 1e9;
  const auto clampb = [big](double v) { return std::min(std::max(v, -big), big); };
  const double fx0 = bounded ? std::floor(clampb(lo_x) - 0.5) - 1 : -big;
  const double fx1 = bounded ? std::floor(clampb(hi_x) - 0.5) + 2 : big;
  const double fy0 = bounded ? std::floor(clampb(lo_y) - 0.5) - 1 : -big;
  const double fy1 = bounded ? std::floor(clampb(hi_y) - 0.5) + 2 : big;
  const int64_t x0 = std::max<int64_t>(std::max(static_cast<int64_t>(fx0), rect[0] * kTile), 0);
  const int64_t y0 = std::max<int64_t>(std::max(static_cast<int64_t>(fy0), rect[1] * kTile), 0);
  int64_t x1 = std::min(static_cast<int64_t>(fx1), std::min(rect[2] * kTile, W));
  int64_t y1 = std::min(static_cast<int64_t>(fy1), std::min(rect[3] * kTile, H));
  if (o < kAlphaMin || x1 <= x0 || y1 <= y0) {
    x1 = x0;
    y1 = y0;
  }
  box[0] = x0;
  box[1] = y0;
  box[2] = x1;
  box[3] = y1;
}

// Stable LSD radix sort of vals by unsigned keys (8-bit digits; digits shared by all keys are skipped).
template <typename U>
void radix_sort(std::vector<U>& keys, std::vector<int32_t>& vals) {
  const size_t n = keys.size();
  std::vector<U> k2(n);
  std::vector<int32_t> v2(n);
  for (unsigned shift = 0; shift < 8 * sizeof(U); shift += 8) {
    size_t cnt[257] = {0};
    for (size_t i = 0; i < n; ++i) cnt[((keys[i] >> shift) & 255u) + 1]++;
    bool trivial = false;
    for (int b = 1; b <= 256; ++b) trivial = trivial || cnt[b] == n;
    if (trivial) continue;
    for (int b = 0; b < 256; ++b) cnt[b + 1] += cnt[b];
    for (size_t i = 0; i < n; ++i) {
      const size_t at = cnt[(keys[i] >> shift) & 255u]++;
      k2[at] = keys[i];
      v2[at] = vals[i];
    }
    keys.swap(k2);
    vals.swap(v2);
  }
}

template <typename S>
using Bits = typename std::conditional<std::is_same<S, float>::value, uint32_t, uint64_t>::type;

template <typename S>
struct ImageSink {  // the image outputs of one camera, (H, W[, ch]) in the input dtype
  S *color, *alpha, *depth, *dsum, *median, *ncam, *nworld, *dist;
  const S* bg;
  const S* R;  // world-to-camera rotation, row-major (normal_world = normal_cam R)
  int64_t D;
  void store(int64_t p, int i, const ForwardScratch& s) {
    const S a = static_cast<S>(s.A[i]), dz = static_cast<S>(s.Dz[i]);
    for (int64_t c = 0; c < D; ++c) color[p * D + c] = static_cast<S>(s.acc[c * kPad + i]) + (S(1) - a) * bg[c];
    alpha[p] = a;
    dsum[p] = dz;
    depth[p] = a > 0 ? dz / a : S(0);
    median[p] = static_cast<S>(s.med[i]);
    dist[p] = static_cast<S>(s.dist[i]);
    S n[3];
    for (int k = 0; k < 3; ++k) {
      n[k] = static_cast<S>(s.acc[(D + k) * kPad + i]);
      ncam[3 * p + k] = n[k];
    }
    for (int k = 0; k < 3; ++k) nworld[3 * p + k] = (n[0] * R[k] + n[1] * R[3 + k]) + n[2] * R[6 + k];
  }
};

void check_render_inputs(const at::Tensor& means, const at::Tensor& quats, const at::Tensor& scales,
                         const at::Tensor& opacities, const at::Tensor& feats, const at::Tensor& means2d,
                         const at::Tensor& bg, const at::Tensor& K, const at::Tensor& w2c) {
  const int64_t N = means.size(0);
  const auto st = means.scalar_type();
  TORCH_CHECK(st == at::kFloat || st == at::kDouble, "surfels_cpu: dtype must be float32 or float64");
  for (const at::Tensor* t : {&means, &quats, &scales, &opacities, &feats, &means2d, &bg, &K, &w2c})
    TORCH_CHECK(t->device().is_cpu() && t->is_contiguous() && t->scalar_type() == st,
                "surfels_cpu: inputs must be contiguous CPU tensors of one dtype");
  TORCH_CHECK(means.dim() == 2 && means.size(1) == 3, "surfels_cpu: means must be (N, 3)");
  TORCH_CHECK(quats.sizes() == at::IntArrayRef({N, 4}) && scales.sizes() == at::IntArrayRef({N, 2}) &&
                  opacities.sizes() == at::IntArrayRef({N}) && means2d.sizes() == at::IntArrayRef({N, 2}),
              "surfels_cpu: quats (N, 4), scales (N, 2), opacities (N,), means2d (N, 2) expected");
  TORCH_CHECK(feats.dim() == 2 && feats.size(0) == N && bg.dim() == 1 && bg.size(0) == feats.size(1),
              "surfels_cpu: feats (N, D) and background (D,) expected");
  TORCH_CHECK(K.sizes() == at::IntArrayRef({3, 3}) && w2c.sizes() == at::IntArrayRef({4, 4}),
              "surfels_cpu: K (3, 3) and w2c (4, 4) expected");
}

template <typename F>
void for_surfels(int64_t n, const F& f) {
  const int nth = num_threads();
#pragma omp parallel for schedule(static) num_threads(nth) if (n >= kParallelSurfels && nth > 1)
  for (int64_t i = 0; i < n; ++i) f(i);
}

// Outputs: color (H, W, D), alpha, depth, depth_sum, median (H, W), normal_cam, normal_world,
// surf_normal_cam, surf_normal_world (H, W, 3), distortion (H, W), visible (N,) bool, radii (N,) int32,
// composited pairs (0-dim int64); then what the backward needs: table (N, 12), payload (N, D + 3),
// boxes (N, 4) (rows of invisible surfels unused), offsets and lists of the tiles (surfel indices in
// centre-depth order), aux, auxi, cmask.
std::vector<at::Tensor> render_forward(const at::Tensor& means, const at::Tensor& quats, const at::Tensor& scales,
                                       const at::Tensor& opacities, const at::Tensor& feats,
                                       const at::Tensor& means2d, const at::Tensor& bg, const at::Tensor& K,
                                       const at::Tensor& w2c, int64_t width, int64_t height, double near,
                                       double far) {
  check_render_inputs(means, quats, scales, opacities, feats, means2d, bg, K, w2c);
  TORCH_CHECK(width > 0 && height > 0, "surfels_cpu: image size must be positive");
  const int64_t N = means.size(0), D = feats.size(1), P = D + 3, H = height, W = width;
  const auto opt = means.options();
  at::Tensor color = at::empty({H, W, D}, opt), alpha = at::empty({H, W}, opt), depth = at::empty({H, W}, opt);
  at::Tensor dsum = at::empty({H, W}, opt), median = at::empty({H, W}, opt), dist = at::empty({H, W}, opt);
  at::Tensor ncam = at::empty({H, W, 3}, opt), nworld = at::empty({H, W, 3}, opt);
  at::Tensor sncam = at::empty({H, W, 3}, opt), snworld = at::empty({H, W, 3}, opt);
  at::Tensor visible = at::empty({N}, opt.dtype(at::kBool)), radii = at::empty({N}, opt.dtype(at::kInt));
  const Grid grid = make_grid(W, H);
  const int64_t nt = grid.tiles();
  at::Tensor aux = at::empty({nt, kAux, kPad}, opt.dtype(at::kDouble));
  at::Tensor auxi = at::empty({nt, kAuxI, kTilePx}, opt.dtype(at::kInt));
  at::Tensor table, payload, boxes, cmask;
  std::vector<at::Tensor> bins;
  int64_t n_pairs = 0;
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "surfels_cpu_render_forward", [&] {
    using S = scalar_t;
    const Camera<S> cam = make_camera<S>(K.data_ptr<S>(), w2c.data_ptr<S>(), W, H, near);
    const S *mp = means.data_ptr<S>(), *qp = quats.data_ptr<S>(), *sp = scales.data_ptr<S>();
    const S *op = opacities.data_ptr<S>(), *fp = feats.data_ptr<S>(), *m2p = means2d.data_ptr<S>();
    // per surfel (rows in surfel order; only visible surfels are ever listed in a tile): the table
    // Tu - c_x Tw, Tv - c_y Tw, Tw, c, o, the payload (features, camera-facing normal) and the
    // candidate pixel box; and the centre depth of the visible ones
    table = at::empty({N, 12}, opt);
    payload = at::empty({N, P}, opt);
    boxes = at::empty({N, 4}, opt.dtype(at::kLong));
    S *tb = table.data_ptr<S>(), *pl = payload.data_ptr<S>();
    int64_t* bx = boxes.data_ptr<int64_t>();
    S* zc = workspace<S>(kWsRec, N, false);
    bool* vis = visible.data_ptr<bool>();
    int32_t* rad = radii.data_ptr<int32_t>();
    for_surfels(N, [&](int64_t r) {
      SurfelProj<S> p;
      project_surfel<S>(mp + 3 * r, qp + 4 * r, sp + 2 * r, m2p + 2 * r, cam, p);
      int64_t radius, rect[4];
      vis[r] = surfel_rect<S>(p, cam, radius, rect);
      rad[r] = static_cast<int32_t>(radius);
      zc[r] = p.pc[2];
      int64_t* box = bx + 4 * r;
      if (!vis[r]) {
        for (int k = 0; k < 4; ++k) box[k] = 0;
        return;
      }
      S* g = tb + 12 * r;
      for (int i = 0; i < 3; ++i) {
        g[i] = p.Tu[i] - p.cx * p.Tw[i];
        g[3 + i] = p.Tv[i] - p.cy * p.Tw[i];
        g[6 + i] = p.Tw[i];
      }
      g[9] = p.cx;
      g[10] = p.cy;
      g[11] = op[r];
      for (int64_t c = 0; c < D; ++c) pl[P * r + c] = fp[D * r + c];
      for (int i = 0; i < 3; ++i) pl[P * r + D + i] = p.n[i] * p.sign;
      candidate_box<S>(p.Tu, p.Tv, p.Tw, p.cx, p.cy, op[r], rect, W, H, box);
    });
    // visible surfels in order of centre depth (> near > 0, so the bit patterns sort like the values)
    std::vector<int32_t> order;
    std::vector<Bits<S>> keys;
    for (int64_t r = 0; r < N; ++r) {
      if (!vis[r]) continue;
      order.push_back(static_cast<int32_t>(r));
      Bits<S> k;
      std::memcpy(&k, zc + r, sizeof(S));
      keys.push_back(k);
    }
    radix_sort(keys, order);
    bins = bin_tiles_impl(boxes, grid, &order);
    cmask = new_cmask(bins[1]);
    const Kernel<S> in = make_kernel<S>(table, payload, boxes, bins[0], bins[1], cmask, grid, near, far);
    ImageSink<S> sink{color.data_ptr<S>(), alpha.data_ptr<S>(),  depth.data_ptr<S>(),  dsum.data_ptr<S>(),
                      median.data_ptr<S>(), ncam.data_ptr<S>(),  nworld.data_ptr<S>(), dist.data_ptr<S>(),
                      bg.data_ptr<S>(),     cam.R,               D};
    n_pairs = run_forward<S>(in, aux.data_ptr<double>(), auxi.data_ptr<int32_t>(), sink);
    // normals from depth, times alpha, and their world rotation
    const S *dp = depth.data_ptr<S>(), *ap = alpha.data_ptr<S>();
    DepthNormalGeom geo{H, W, {}};
    std::copy(cam.Kinv, cam.Kinv + 9, geo.ki);
    S *sc = sncam.data_ptr<S>(), *sw = snworld.data_ptr<S>();
    const S* Rc = cam.R;
    dn_forward(geo, dp, [sc, sw, ap, Rc](int64_t p, const double* v) {
      S n[3];
      for (int k = 0; k < 3; ++k) {
        n[k] = static_cast<S>(v[k]) * ap[p];
        sc[3 * p + k] = n[k];
      }
      for (int k = 0; k < 3; ++k) sw[3 * p + k] = (n[0] * Rc[k] + n[1] * Rc[3 + k]) + n[2] * Rc[6 + k];
    });
  });
  at::Tensor pairs = at::empty({}, opt.dtype(at::kLong));
  pairs.fill_(n_pairs);
  return {color, alpha, depth,   dsum,  median,  ncam, nworld, sncam, snworld, dist, visible,
          radii, pairs, table, payload, boxes, bins[0], bins[1], aux,  auxi, cmask};
}

// A gradient of an image output, (H, W) or (H, W, C), any strides (autograd often passes expanded
// tensors); absent gradients read as 0.
template <typename S>
struct ImGrad {
  const S* ptr = nullptr;
  int64_t sy = 0, sx = 0, sc = 0;
  bool defined() const { return ptr != nullptr; }
  double operator()(int64_t y, int64_t x, int64_t c = 0) const {
    return ptr != nullptr ? static_cast<double>(ptr[y * sy + x * sx + c * sc]) : 0.0;
  }
};

template <typename S>
ImGrad<S> image_grad(const std::optional<at::Tensor>& t, int64_t H, int64_t W, int64_t C, const char* name) {
  ImGrad<S> g;
  if (!t.has_value() || !t->defined()) return g;
  const bool ok = t->scalar_type() == c10::CppTypeToScalarType<S>::value && t->device().is_cpu() &&
                  (C == 0 ? t->sizes() == at::IntArrayRef({H, W}) : t->sizes() == at::IntArrayRef({H, W, C}));
  TORCH_CHECK(ok, "surfels_cpu: gradient of ", name, " has the wrong shape or dtype");
  g.ptr = t->data_ptr<S>();
  g.sy = t->stride(0);
  g.sx = t->stride(1);
  g.sc = C == 0 ? 0 : t->stride(2);
  return g;
}

// Gradients of means (N, 3), quats (N, 4), scales (N, 2), opacities (N,), feats (N, D), means2d (N, 2)
// and background (D,) from the gradients of the ten image outputs (any of them may be absent).
std::vector<at::Tensor> render_backward(
    const at::Tensor& means, const at::Tensor& quats, const at::Tensor& scales, const at::Tensor& opacities,
    const at::Tensor& feats, const at::Tensor& means2d, const at::Tensor& bg, const at::Tensor& K,
    const at::Tensor& w2c, const at::Tensor& visible_t, const at::Tensor& table, const at::Tensor& payload,
    const at::Tensor& boxes, const at::Tensor& offsets, const at::Tensor& lst, const at::Tensor& aux,
    const at::Tensor& auxi, const at::Tensor& cmask, const at::Tensor& alpha, const at::Tensor& depth,
    const at::Tensor& dsum,
    const std::optional<at::Tensor>& g_color, const std::optional<at::Tensor>& g_alpha,
    const std::optional<at::Tensor>& g_depth, const std::optional<at::Tensor>& g_dsum,
    const std::optional<at::Tensor>& g_median, const std::optional<at::Tensor>& g_ncam,
    const std::optional<at::Tensor>& g_nworld, const std::optional<at::Tensor>& g_sncam,
    const std::optional<at::Tensor>& g_snworld, const std::optional<at::Tensor>& g_dist, int64_t width,
    int64_t height, double near, double far) {
  check_render_inputs(means, quats, scales, opacities, feats, means2d, bg, K, w2c);
  check_table_inputs(table, payload, boxes);
  const int64_t N = means.size(0), D = feats.size(1), P = D + 3, H = height, W = width, HW = H * W;
  const int64_t G = 12 + P;
  TORCH_CHECK(table.size(0) == N && payload.size(1) == P && visible_t.numel() == N &&
                  visible_t.scalar_type() == at::kBool && visible_t.is_contiguous(),
              "surfels_cpu: saved buffers do not match the inputs");
  const Grid grid = make_grid(W, H);
  check_aux(aux, auxi, offsets, lst, cmask, grid);
  const auto opt = means.options();
  at::Tensor g_means = at::empty({N, 3}, opt), g_quats = at::empty({N, 4}, opt), g_scales = at::empty({N, 2}, opt);
  at::Tensor g_opac = at::empty({N}, opt), g_feats = at::empty({N, D}, opt), g_m2 = at::empty({N, 2}, opt);
  at::Tensor g_bg = at::empty({D}, opt);
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "surfels_cpu_render_backward", [&] {
    using S = scalar_t;
    const Camera<S> cam = make_camera<S>(K.data_ptr<S>(), w2c.data_ptr<S>(), W, H, near);
    const ImGrad<S> gcol = image_grad<S>(g_color, H, W, D, "color");
    const ImGrad<S> gal = image_grad<S>(g_alpha, H, W, 0, "alpha");
    const ImGrad<S> gdep = image_grad<S>(g_depth, H, W, 0, "depth");
    const ImGrad<S> gds = image_grad<S>(g_dsum, H, W, 0, "depth_sum");
    const ImGrad<S> gmed = image_grad<S>(g_median, H, W, 0, "median_depth");
    const ImGrad<S> gnc = image_grad<S>(g_ncam, H, W, 3, "normal_cam");
    const ImGrad<S> gnw = image_grad<S>(g_nworld, H, W, 3, "normal_world");
    const ImGrad<S> gsc = image_grad<S>(g_sncam, H, W, 3, "surf_normal_cam");
    const ImGrad<S> gsw = image_grad<S>(g_snworld, H, W, 3, "surf_normal_world");
    const ImGrad<S> gdi = image_grad<S>(g_dist, H, W, 0, "distortion");
    const S *ap = alpha.data_ptr<S>(), *dp = depth.data_ptr<S>(), *dsp = dsum.data_ptr<S>(), *bgp = bg.data_ptr<S>();
    const double* R = cam.Rd;
    // 1. image outputs -> per-pixel gradients of the compositing sums (tile-major)
    double* gdn_depth = workspace<double>(kWsDepthGrad, HW, true);
    if (gsc.defined() || gsw.defined()) {
      // surf_normal_cam = normal_from_depth * alpha (alpha detached), surf_normal_world = surf_normal_cam R
      DepthNormalGeom geo{H, W, {}};
      std::copy(cam.Kinv, cam.Kinv + 9, geo.ki);
      dn_backward(geo, dp, [&gsc, &gsw, ap, R, W](int64_t y, int64_t x, double* v) {
        const double a = ap[y * W + x];
        for (int k = 0; k < 3; ++k) {
          double g = gsc(y, x, k);
          if (gsw.defined()) g += (gsw(y, x, 0) * R[3 * k] + gsw(y, x, 1) * R[3 * k + 1]) + gsw(y, x, 2) * R[3 * k + 2];
          v[k] = g * a;
        }
      }, gdn_depth);
    }
    double* gstat = workspace<double>(kWsGstat, grid.tiles() * 4 * kPad, false);
    S* gpix = workspace<S>(kWsGpay, grid.tiles() * P * kPad, false);
    std::vector<double> gbg(static_cast<size_t>(D), 0.0);
    fill_tile_major<S>(grid, gstat, gpix, P, [&](int64_t y, int64_t x, double* st, S* pay) {
      const int64_t p = y * W + x;
      const double a = ap[p], ds = dsp[p];
      const double gd = gdep(y, x) + gdn_depth[p];
      double g_a = gal(y, x), g_d = gds(y, x);
      if (a > 0) {  // depth = depth_sum / alpha
        g_d += gd / a;
        g_a -= gd * ds / (a * a);
      }
      const double one_minus_a = static_cast<double>(S(1) - ap[p]);
      for (int64_t c = 0; c < D; ++c) {
        const double gc = gcol(y, x, c);
        g_a -= gc * static_cast<double>(bgp[c]);
        gbg[c] += gc * one_minus_a;
        pay[c * kPad] = static_cast<S>(gc);
      }
      for (int k = 0; k < 3; ++k) {
        double g = gnc(y, x, k);
        if (gnw.defined()) g += (gnw(y, x, 0) * R[3 * k] + gnw(y, x, 1) * R[3 * k + 1]) + gnw(y, x, 2) * R[3 * k + 2];
        pay[(D + k) * kPad] = static_cast<S>(g);
      }
      st[0] = g_a;
      st[kPad] = g_d;
      st[2 * kPad] = gmed(y, x);
      st[3 * kPad] = gdi(y, x);
    });
    S* gb = g_bg.data_ptr<S>();
    for (int64_t c = 0; c < D; ++c) gb[c] = static_cast<S>(gbg[c]);
    // 2. compositing backward: gradients of the table rows and payload, per visible surfel
    const Kernel<S> in = make_kernel<S>(table, payload, boxes, offsets, lst, cmask, grid, near, far);
    const double* total = run_backward<S>(in, N, aux.data_ptr<double>(), auxi.data_ptr<int32_t>(), gstat, gpix);
    // 3. table and payload -> surfel parameters (total holds a row per surfel)
    const bool* visible = visible_t.data_ptr<bool>();
    const S *mp = means.data_ptr<S>(), *qp = quats.data_ptr<S>(), *sp = scales.data_ptr<S>();
    const S* m2p = means2d.data_ptr<S>();
    S *gm = g_means.data_ptr<S>(), *gq = g_quats.data_ptr<S>(), *gs = g_scales.data_ptr<S>();
    S *go = g_opac.data_ptr<S>(), *gf = g_feats.data_ptr<S>(), *g2 = g_m2.data_ptr<S>();
    const double* Kd = cam.Kd;
    const double c2 = kCutoff2;
    for_surfels(N, [&](int64_t r) {
      if (!visible[r]) {
        std::fill(gm + 3 * r, gm + 3 * r + 3, S(0));
        std::fill(gq + 4 * r, gq + 4 * r + 4, S(0));
        std::fill(gs + 2 * r, gs + 2 * r + 2, S(0));
        std::fill(g2 + 2 * r, g2 + 2 * r + 2, S(0));
        std::fill(gf + D * r, gf + D * r + D, S(0));
        go[r] = S(0);
        return;
      }
      const double* gt = total + G * r;
      SurfelProj<S> p;
      project_surfel<S>(mp + 3 * r, qp + 4 * r, sp + 2 * r, m2p + 2 * r, cam, p);
      double Tu[3], Tv[3], Tw[3];
      for (int i = 0; i < 3; ++i) {
        Tu[i] = p.Tu[i];
        Tv[i] = p.Tv[i];
        Tw[i] = p.Tw[i];
      }
      const double cx = p.cx, cy = p.cy, d = p.d;
      // table rows Tu - c_x Tw, Tv - c_y Tw, Tw, c, o
      double gTu[3], gTv[3], gTw[3];
      for (int i = 0; i < 3; ++i) {
        gTu[i] = gt[i];
        gTv[i] = gt[3 + i];
        gTw[i] = gt[6 + i] - cx * gt[i] - cy * gt[3 + i];
      }
      const double gcx = gt[9] - ((Tw[0] * gt[0] + Tw[1] * gt[1]) + Tw[2] * gt[2]);
      const double gcy = gt[10] - ((Tw[0] * gt[3] + Tw[1] * gt[4]) + Tw[2] * gt[5]);
      // centre c = (c2 (Tu0 Tw0 + Tu1 Tw1) - Tu2 Tw2, same with Tv) / d, d = c2 (Tw0^2 + Tw1^2) - Tw2^2
      const double ex = gcx / d, ey = gcy / d;
      for (int i = 0; i < 2; ++i) {
        gTu[i] += ex * c2 * Tw[i];
        gTv[i] += ey * c2 * Tw[i];
        gTw[i] += ex * (c2 * Tu[i] - 2.0 * c2 * cx * Tw[i]) + ey * (c2 * Tv[i] - 2.0 * c2 * cy * Tw[i]);
      }
      gTu[2] -= ex * Tw[2];
      gTv[2] -= ey * Tw[2];
      gTw[2] += ex * (2.0 * cx * Tw[2] - Tu[2]) + ey * (2.0 * cy * Tw[2] - Tv[2]);
      // M = K [a | b | p_c] with (Tu[2], Tv[2]) = means2d z_s
      const double zs = p.zs, m2x = m2p[2 * r], m2y = m2p[2 * r + 1];
      g2[2 * r] = static_cast<S>(gTu[2] * zs);
      g2[2 * r + 1] = static_cast<S>(gTv[2] * zs);
      double ga[3], gbv[3], gpc[3], gn[3];
      for (int j = 0; j < 3; ++j) {
        ga[j] = (Kd[j] * gTu[0] + Kd[3 + j] * gTv[0]) + Kd[6 + j] * gTw[0];
        gbv[j] = (Kd[j] * gTu[1] + Kd[3 + j] * gTv[1]) + Kd[6 + j] * gTw[1];
        gpc[j] = Kd[6 + j] * gTw[2];
        gn[j] = static_cast<double>(p.sign) * gt[12 + D + j];
      }
      if (p.zok) gpc[2] += gTu[2] * m2x + gTv[2] * m2y;
      // a = Rcw t_u s_u, b = Rcw t_v s_v, n = Rcw t_w, p_c = Rcw mean + t
      double va[3], vb[3], vn[3];
      for (int j = 0; j < 3; ++j) {
        va[j] = (R[j] * ga[0] + R[3 + j] * ga[1]) + R[6 + j] * ga[2];
        vb[j] = (R[j] * gbv[0] + R[3 + j] * gbv[1]) + R[6 + j] * gbv[2];
        vn[j] = (R[j] * gn[0] + R[3 + j] * gn[1]) + R[6 + j] * gn[2];
        gm[3 * r + j] = static_cast<S>((R[j] * gpc[0] + R[3 + j] * gpc[1]) + R[6 + j] * gpc[2]);
      }
      const double s0 = sp[2 * r], s1 = sp[2 * r + 1];
      double Rq[9];
      for (int i = 0; i < 9; ++i) Rq[i] = p.R[i];
      gs[2 * r] = static_cast<S>((Rq[0] * va[0] + Rq[3] * va[1]) + Rq[6] * va[2]);
      gs[2 * r + 1] = static_cast<S>((Rq[1] * vb[0] + Rq[4] * vb[1]) + Rq[7] * vb[2]);
      double GR[9];  // dL/dR, row-major
      for (int i = 0; i < 3; ++i) {
        GR[3 * i] = va[i] * s0;
        GR[3 * i + 1] = vb[i] * s1;
        GR[3 * i + 2] = vn[i];
      }
      // R(q) of the unit quaternion, then the normalisation q / max(|q|, 1e-12)
      const double w = p.q[0], x = p.q[1], y = p.q[2], z = p.q[3];
      double gqn[4];
      gqn[0] = 2.0 * (-z * GR[1] + y * GR[2] + z * GR[3] - x * GR[5] - y * GR[6] + x * GR[7]);
      gqn[1] = 2.0 * (y * GR[1] + z * GR[2] + y * GR[3] - 2.0 * x * GR[4] - w * GR[5] + z * GR[6] + w * GR[7] -
                      2.0 * x * GR[8]);
      gqn[2] = 2.0 * (-2.0 * y * GR[0] + x * GR[1] + w * GR[2] + x * GR[3] + z * GR[5] - w * GR[6] + z * GR[7] -
                      2.0 * y * GR[8]);
      gqn[3] = 2.0 * (-2.0 * z * GR[0] - w * GR[1] + x * GR[2] + w * GR[3] - 2.0 * z * GR[4] + y * GR[5] +
                      x * GR[6] + y * GR[7]);
      const double norm = p.norm;
      if (p.norm > static_cast<S>(1e-12)) {
        const double dq = ((w * gqn[0] + x * gqn[1]) + y * gqn[2]) + z * gqn[3];
        for (int i = 0; i < 4; ++i) gq[4 * r + i] = static_cast<S>((gqn[i] - p.q[i] * dq) / norm);
      } else {
        for (int i = 0; i < 4; ++i) gq[4 * r + i] = static_cast<S>(gqn[i] / static_cast<double>(static_cast<S>(1e-12)));
      }
      go[r] = static_cast<S>(gt[11]);
      for (int64_t c = 0; c < D; ++c) gf[D * r + c] = static_cast<S>(gt[12 + c]);
    });
  });
  return {g_means, g_quats, g_scales, g_opac, g_feats, g_m2, g_bg};
}

// means2d (C, N, 2), or (N, 2) with squeeze (C = 1): the projected surfel centres (K p_c)[:2] / z_s, z_s = p_c,z or 1 when |p_c,z| <= 1e-12.
at::Tensor means2d_forward(const at::Tensor& means, const at::Tensor& K, const at::Tensor& w2c, bool squeeze) {
  TORCH_CHECK(means.dim() == 2 && means.size(1) == 3 && K.dim() == 3 && K.size(1) == 3 && K.size(2) == 3 &&
                  w2c.dim() == 3 && w2c.size(0) == K.size(0) && w2c.size(1) == 4 && w2c.size(2) == 4,
              "surfels_cpu: means (N, 3), K (C, 3, 3), w2c (C, 4, 4) expected");
  for (const at::Tensor* t : {&means, &K, &w2c})
    TORCH_CHECK(t->device().is_cpu() && t->is_contiguous() && t->scalar_type() == means.scalar_type(),
                "surfels_cpu: inputs must be contiguous CPU tensors of one dtype");
  const int64_t N = means.size(0), C = K.size(0);
  TORCH_CHECK(!squeeze || C == 1, "surfels_cpu: squeeze needs one camera");
  at::Tensor out = squeeze ? at::empty({N, 2}, means.options()) : at::empty({C, N, 2}, means.options());
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "surfels_cpu_means2d", [&] {
    using S = scalar_t;
    const S* mp = means.data_ptr<S>();
    S* o = out.data_ptr<S>();
    for (int64_t c = 0; c < C; ++c) {
      const Camera<S> cam = make_camera<S>(K.data_ptr<S>() + 9 * c, w2c.data_ptr<S>() + 16 * c, 1, 1, 1.0);
      for_surfels(N, [&](int64_t r) {
        S pc[3];
        for (int i = 0; i < 3; ++i) pc[i] = dot3(cam.R + 3 * i, mp + 3 * r) + cam.t[i];
        const S zs = std::fabs(pc[2]) > static_cast<S>(1e-12) ? pc[2] : S(1);
        o[(c * N + r) * 2] = dot3(cam.K, pc) / zs;
        o[(c * N + r) * 2 + 1] = dot3(cam.K + 3, pc) / zs;
      });
    }
  });
  return out;
}

// Gradient of means2d_forward: grad (C, N, 2) -> d means (N, 3), summed over the cameras in order.
at::Tensor means2d_backward(const at::Tensor& means, const at::Tensor& K, const at::Tensor& w2c,
                            const at::Tensor& grad) {
  const int64_t N = means.size(0), C = K.size(0);
  TORCH_CHECK(grad.sizes() == at::IntArrayRef({C, N, 2}) && grad.is_contiguous() &&
                  grad.scalar_type() == means.scalar_type(),
              "surfels_cpu: grad must be a contiguous (C, N, 2) tensor of the means' dtype");
  at::Tensor out = at::zeros({N, 3}, means.options());
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "surfels_cpu_means2d_backward", [&] {
    using S = scalar_t;
    const S* mp = means.data_ptr<S>();
    const S* gp = grad.data_ptr<S>();
    S* o = out.data_ptr<S>();
    std::vector<double> acc(static_cast<size_t>(3 * N), 0.0);
    for (int64_t c = 0; c < C; ++c) {
      const Camera<S> cam = make_camera<S>(K.data_ptr<S>() + 9 * c, w2c.data_ptr<S>() + 16 * c, 1, 1, 1.0);
      for_surfels(N, [&](int64_t r) {
        S pc[3];
        for (int i = 0; i < 3; ++i) pc[i] = dot3(cam.R + 3 * i, mp + 3 * r) + cam.t[i];
        const bool zok = std::fabs(pc[2]) > static_cast<S>(1e-12);
        const double zs = zok ? static_cast<double>(pc[2]) : 1.0;
        const double gx = gp[(c * N + r) * 2], gy = gp[(c * N + r) * 2 + 1];
        const double mx = dot3(cam.K, pc) / static_cast<S>(zs), my = dot3(cam.K + 3, pc) / static_cast<S>(zs);
        double gpc[3];
        for (int j = 0; j < 3; ++j) gpc[j] = (cam.Kd[j] * gx + cam.Kd[3 + j] * gy) / zs;
        if (zok) gpc[2] -= (mx * gx + my * gy) / zs;
        for (int j = 0; j < 3; ++j)
          acc[3 * r + j] += (cam.Rd[j] * gpc[0] + cam.Rd[3 + j] * gpc[1]) + cam.Rd[6 + j] * gpc[2];
      });
    }
    for (int64_t i = 0; i < 3 * N; ++i) o[i] = static_cast<S>(acc[i]);
  });
  return out;
}

}  // namespace

TORCH_LIBRARY(sage_surfels_cpu, m) {
  m.def(
      "render_forward(Tensor means, Tensor quats, Tensor scales, Tensor opacities, Tensor feats, Tensor means2d, "
      "Tensor background, Tensor K, Tensor w2c, int width, int height, float near, float far) -> Tensor[]",
      &render_forward);
  m.def(
      "render_backward(Tensor means, Tensor quats, Tensor scales, Tensor opacities, Tensor feats, Tensor means2d, "
      "Tensor background, Tensor K, Tensor w2c, Tensor visible, Tensor table, Tensor payload, Tensor boxes, "
      "Tensor offsets, Tensor lst, Tensor aux, Tensor auxi, Tensor cmask, Tensor alpha, Tensor depth, Tensor depth_sum, "
      "Tensor? g_color, Tensor? g_alpha, Tensor? g_depth, Tensor? g_depth_sum, Tensor? g_median, "
      "Tensor? g_normal_cam, Tensor? g_normal_world, Tensor? g_surf_normal_cam, Tensor? g_surf_normal_world, "
      "Tensor? g_distortion, int width, int height, float near, float far) -> Tensor[]",
      &render_backward);
  m.def("means2d_forward(Tensor means, Tensor K, Tensor w2c, bool squeeze) -> Tensor", &means2d_forward);
  m.def("means2d_backward(Tensor means, Tensor K, Tensor w2c, Tensor grad) -> Tensor", &means2d_backward);
  m.def("forward(Tensor table, Tensor payload, Tensor boxes, int width, int height, float near, float far) -> Tensor[]",
        &composite_forward);
  m.def(
      "backward(Tensor table, Tensor payload, Tensor boxes, Tensor offsets, Tensor lst, Tensor aux, Tensor auxi, "
      "Tensor cmask, Tensor g_pay, Tensor g_stats, int width, int height, float near, float far) -> Tensor[]",
      &composite_backward);
  m.def("bin_tiles(Tensor boxes, int width, int height) -> Tensor[]", &bin_tiles);
  m.def("depth_normal_forward(Tensor depth, Tensor kinv) -> Tensor", &depth_normal_forward);
  m.def("depth_normal_backward(Tensor depth, Tensor kinv, Tensor grad) -> Tensor", &depth_normal_backward);
  m.def("max_threads() -> int", &max_threads);
  m.def("use_avx2(bool on) -> bool", &use_avx2);
}

#else  // SG_SURFELS_KERNEL_BODY: the tile loops, included twice above

// ------------------------------------------------------------------------------------------------
// Lanes: 8 pixels of a tile row, held as a pack of native vectors of the instruction set the tile
// loop is built for (AVX2: one 8-float or two 4-double vectors; SSE2: two 4-float or four 2-double
// vectors), so that every operation, comparison and select maps to vector instructions.

template <typename V, int K>
struct Pack {
  V v[K];
};

template <typename V>
using elem_t = std::remove_cv_t<std::remove_reference_t<decltype(std::declval<V>()[0])>>;

#define SG_PACK_BINOP(op)                                                      \
  template <typename V, int K>                                                 \
  SG_INLINE Pack<V, K> operator op(const Pack<V, K>& a, const Pack<V, K>& b) { \
    Pack<V, K> r;                                                              \
    for (int i = 0; i < K; ++i) r.v[i] = a.v[i] op b.v[i];                     \
    return r;                                                                  \
  }                                                                            \
  template <typename V, int K>                                                 \
  SG_INLINE Pack<V, K> operator op(const Pack<V, K>& a, elem_t<V> b) {         \
    Pack<V, K> r;                                                              \
    for (int i = 0; i < K; ++i) r.v[i] = a.v[i] op b;                          \
    return r;                                                                  \
  }                                                                            \
  template <typename V, int K>                                                 \
  SG_INLINE Pack<V, K> operator op(elem_t<V> a, const Pack<V, K>& b) {         \
    Pack<V, K> r;                                                              \
    for (int i = 0; i < K; ++i) r.v[i] = a op b.v[i];                          \
    return r;                                                                  \
  }
SG_PACK_BINOP(+)
SG_PACK_BINOP(-)
SG_PACK_BINOP(*)
SG_PACK_BINOP(/)
SG_PACK_BINOP(&)
SG_PACK_BINOP(|)
#undef SG_PACK_BINOP

#define SG_PACK_CMP(op)                                                                            \
  template <typename V, int K>                                                                     \
  SG_INLINE auto operator op(const Pack<V, K>& a, const Pack<V, K>& b) {                           \
    Pack<decltype(a.v[0] op b.v[0]), K> r;                                                         \
    for (int i = 0; i < K; ++i) r.v[i] = a.v[i] op b.v[i];                                         \
    return r;                                                                                      \
  }                                                                                                \
  template <typename V, int K>                                                                     \
  SG_INLINE auto operator op(const Pack<V, K>& a, elem_t<V> b) {                                   \
    Pack<decltype(a.v[0] op a.v[0]), K> r;                                                         \
    for (int i = 0; i < K; ++i) r.v[i] = a.v[i] op b;                                              \
    return r;                                                                                      \
  }
SG_PACK_CMP(<)
SG_PACK_CMP(<=)
SG_PACK_CMP(>)
SG_PACK_CMP(>=)
SG_PACK_CMP(==)
SG_PACK_CMP(!=)
#undef SG_PACK_CMP

template <typename V, int K>
SG_INLINE Pack<V, K> operator-(const Pack<V, K>& a) {
  Pack<V, K> r;
  for (int i = 0; i < K; ++i) r.v[i] = -a.v[i];
  return r;
}
template <typename V, int K>
SG_INLINE Pack<V, K> operator~(const Pack<V, K>& a) {
  Pack<V, K> r;
  for (int i = 0; i < K; ++i) r.v[i] = ~a.v[i];
  return r;
}
// m ? a : b per lane; m holds 0 or -1 in integers of the lanes' width.
template <typename M, typename V, int K>
SG_INLINE Pack<V, K> select(const Pack<M, K>& m, const Pack<V, K>& a, const Pack<V, K>& b) {
  Pack<V, K> r;
  for (int i = 0; i < K; ++i) r.v[i] = m.v[i] ? a.v[i] : b.v[i];
  return r;
}
template <typename P, typename E>
SG_INLINE P splat(E x) {
  using V = std::remove_reference_t<decltype(std::declval<P>().v[0])>;
  constexpr int K = sizeof(P) / sizeof(V);
  P p;
  for (int i = 0; i < K; ++i)
    for (int k = 0; k < static_cast<int>(sizeof(V) / sizeof(elem_t<V>)); ++k) p.v[i][k] = static_cast<elem_t<V>>(x);
  return p;
}
// Unaligned loads and stores, one native vector at a time.
template <typename P, typename E>
SG_INLINE P load(const E* ptr) {
  using V = std::remove_reference_t<decltype(std::declval<P>().v[0])>;
  constexpr int K = sizeof(P) / sizeof(V);
  P p;
  for (int i = 0; i < K; ++i) std::memcpy(&p.v[i], reinterpret_cast<const char*>(ptr) + i * sizeof(V), sizeof(V));
  return p;
}
template <typename P, typename E>
SG_INLINE void store(E* ptr, const P& p) {
  using V = std::remove_reference_t<decltype(std::declval<P>().v[0])>;
  constexpr int K = sizeof(P) / sizeof(V);
  for (int i = 0; i < K; ++i) std::memcpy(reinterpret_cast<char*>(ptr) + i * sizeof(V), &p.v[i], sizeof(V));
}

// exp(x) for x <= 0 in float64 (for float64 inputs): x = n ln2 + r, |r| <= ln2 / 2, Taylor polynomial
// of degree DEG in r (13 gives < 1e-17 relative error), times 2^n through the exponent bits. Inputs
// below -100 are treated as -100 (exp(-100) ~ 4e-44; callers only use values where o exp(x) >= 1/255).
template <int DEG, typename Dv>
SG_INLINE Dv exp_neg_v(Dv x) {
  using Lv = decltype(x < x);
  constexpr int n = sizeof(Dv) / sizeof(double);
  Dv lo, magic;
  for (int k = 0; k < n; ++k) {
    lo[k] = -100.0;
    magic[k] = 6755399441055744.0;  // 1.5 * 2^52: adding it rounds to an integer
  }
  x = x < lo ? lo : x;
  const Dv t = x * 1.4426950408889634 + magic;
  const Dv nn = t - magic;
  Dv r = x - nn * 6.93147180369123816490e-01;
  r = r - nn * 1.90821492927058770002e-10;
  double c[DEG + 1];
  c[0] = 1.0;
  for (int k = 1; k <= DEG; ++k) c[k] = c[k - 1] / k;
  Dv p = r * c[DEG] + c[DEG - 1];
  for (int k = DEG - 2; k >= 0; --k) p = p * r + c[k];
  const Lv e = ((Lv)t - (Lv)magic) << 52;
  return (Dv)((Lv)p + e);
}
// exp(x) for x <= 0 in float32 (for float32 inputs): the same reduction with a two-part float ln2
// and a Taylor polynomial of degree 7 (within about one float ulp of exp). Inputs below -87 are
// treated as -87.
template <typename Fv>
SG_INLINE Fv exp_neg_f(Fv x) {
  using Iv = decltype(x < x);
  constexpr int n = sizeof(Fv) / sizeof(float);
  Fv lo, magic;
  for (int k = 0; k < n; ++k) {
    lo[k] = -87.0f;
    magic[k] = 12582912.0f;  // 1.5 * 2^23
  }
  x = x < lo ? lo : x;
  const Fv t = x * 1.44269504f + magic;
  const Fv nn = t - magic;
  Fv r = x - nn * 0.693359375f;
  r = r - nn * -2.12194440e-4f;
  constexpr float c[8] = {1.0f, 1.0f, 0.5f, 1.0f / 6, 1.0f / 24, 1.0f / 120, 1.0f / 720, 1.0f / 5040};
  Fv p = r * c[7] + c[6];
  for (int k = 5; k >= 0; --k) p = p * r + c[k];
  const Iv e = ((Iv)t - (Iv)magic) << 23;
  return (Fv)((Iv)p + e);
}
template <typename V, int K>
SG_INLINE Pack<V, K> exp_neg_lanes(const Pack<V, K>& x) {
  Pack<V, K> r;
  for (int i = 0; i < K; ++i) {
    if constexpr (std::is_same<elem_t<V>, float>::value)
      r.v[i] = exp_neg_f(x.v[i]);
    else
      r.v[i] = exp_neg_v<13>(x.v[i]);
  }
  return r;
}

// Native vectors of AVX2: 8 floats, or 4 doubles (two per pack of 8 lanes). (The conversions are
// written in the forms GCC turns into single vcvtps2pd / vcvtpd2ps instructions.)
struct IsaAvx2 {
  typedef float Fv __attribute__((vector_size(32)));
  typedef float F4 __attribute__((vector_size(16)));
  typedef double Dv __attribute__((vector_size(32)));
  typedef double D8 __attribute__((vector_size(64)));
  typedef int64_t Lv __attribute__((vector_size(32)));
  using F = Pack<Fv, 1>;
  using D = Pack<Dv, 2>;
  using M = Pack<Lv, 2>;  // masks of D lanes
  static SG_INLINE D widen(const F& f) {
    const D8 w = __builtin_convertvector(f.v[0], D8);
    D d;
    d.v[0] = __builtin_shufflevector(w, w, 0, 1, 2, 3);
    d.v[1] = __builtin_shufflevector(w, w, 4, 5, 6, 7);
    return d;
  }
  static SG_INLINE F narrow(const D& d) {
    const F4 lo = __builtin_convertvector(d.v[0], F4), hi = __builtin_convertvector(d.v[1], F4);
    F f;
    f.v[0] = __builtin_shufflevector(lo, hi, 0, 1, 2, 3, 4, 5, 6, 7);
    return f;
  }
};

// Native vectors of SSE2 (every x86-64 CPU): 4 floats, or 2 doubles.
struct IsaSse2 {
  typedef float Fv __attribute__((vector_size(16)));
  typedef double Dv __attribute__((vector_size(16)));
  typedef double D4 __attribute__((vector_size(32)));
  typedef int64_t Lv __attribute__((vector_size(16)));
  using F = Pack<Fv, 2>;
  using D = Pack<Dv, 4>;
  using M = Pack<Lv, 4>;
  static SG_INLINE D widen(const F& f) {
    D d;
    for (int i = 0; i < 2; ++i) {
      const D4 w = __builtin_convertvector(f.v[i], D4);
      d.v[2 * i] = __builtin_shufflevector(w, w, 0, 1);
      d.v[2 * i + 1] = __builtin_shufflevector(w, w, 2, 3);
    }
    return d;
  }
  static SG_INLINE F narrow(const D& d) {
    F f;
    for (int i = 0; i < 2; ++i)
      f.v[i] = __builtin_convertvector(__builtin_shufflevector(d.v[2 * i], d.v[2 * i + 1], 0, 1, 2, 3), Fv);
    return f;
  }
};

// The lanes of a mask as bits (lane k -> bit k; kLaneMasks turns bits back into lanes), and whether
// any lane is set.
#if SG_SURFELS_AVX2
SG_INLINE int lane_bits(const IsaAvx2::M& m) {
  return _mm256_movemask_pd((__m256d)m.v[0]) | (_mm256_movemask_pd((__m256d)m.v[1]) << 4);
}
SG_INLINE bool any(const IsaAvx2::M& m) {
  const __m256i o = _mm256_or_si256((__m256i)m.v[0], (__m256i)m.v[1]);
  return !_mm256_testz_si256(o, o);
}
#else
SG_INLINE int lane_bits(const IsaSse2::M& m) {
  int b = 0;
  for (int i = 0; i < 4; ++i) b |= _mm_movemask_pd((__m128d)m.v[i]) << (2 * i);
  return b;
}
SG_INLINE bool any(const IsaSse2::M& m) {
  const __m128i o = _mm_or_si128(_mm_or_si128((__m128i)m.v[0], (__m128i)m.v[1]),
                                 _mm_or_si128((__m128i)m.v[2], (__m128i)m.v[3]));
  return _mm_movemask_epi8(o) != 0;
}
#endif

// The geometry lanes V in the input dtype, and their conversion to and from float64 lanes.
template <typename S, typename Isa>
struct Lanes;
template <typename Isa>
struct Lanes<float, Isa> {
  using V = typename Isa::F;
  static SG_INLINE typename Isa::D to_d(const V& v) { return Isa::widen(v); }
  static SG_INLINE V from_d(const typename Isa::D& d) { return Isa::narrow(d); }
};
template <typename Isa>
struct Lanes<double, Isa> {
  using V = typename Isa::D;
  static SG_INLINE typename Isa::D to_d(const V& v) { return v; }
  static SG_INLINE V from_d(const typename Isa::D& d) { return d; }
};

// Ray-splat intersection, low-pass filter and alpha of one surfel at the 8 pixel centres of a row
// chunk (eval_pairs of the packed backend), in the input dtype. g: the surfel's 12 table values
// (Tu - c_x Tw, Tv - c_y Tw, Tw, c_x, c_y, o); xs: pixel-centre x of the lanes; dy = y - c_y and
// l = dy Tw - (Tv - c_y Tw) of the row. hz is h_z with 1 where h_z = 0 (hz0 flags those lanes).
template <typename S, typename Isa>
struct Geo {
  using V = typename Lanes<S, Isa>::V;
  V dx, k0, k1, k2, hz, hz_raw, u, v, rho2d, rho3d, ex, G, alpha, z;
};

template <typename S, typename Isa>
SG_INLINE void eval_lanes(const S* g, const typename Lanes<S, Isa>::V& xs, S dy, S l0, S l1, S l2, Geo<S, Isa>& h) {
  using V = typename Lanes<S, Isa>::V;
  const S tu0 = g[0], tu1 = g[1], tu2 = g[2];
  const S tw0 = g[6], tw1 = g[7], tw2 = g[8], cx = g[9], o = g[11];
  h.dx = xs - cx;
  h.k0 = h.dx * tw0 - tu0;
  h.k1 = h.dx * tw1 - tu1;
  h.k2 = h.dx * tw2 - tu2;
  const V hx = h.k1 * l2 - h.k2 * l1;
  const V hy = h.k2 * l0 - h.k0 * l2;
  h.hz_raw = h.k0 * l1 - h.k1 * l0;
  const auto hz_ok = h.hz_raw != S(0);
  h.hz = select(hz_ok, h.hz_raw, splat<V>(S(1)));
  h.u = hx / h.hz;
  h.v = hy / h.hz;
  h.rho2d = S(2) * (h.dx * h.dx + dy * dy);
  h.rho3d = h.u * h.u + h.v * h.v;
  const auto use3d = hz_ok & (h.rho3d <= h.rho2d);
  const V rho = select(use3d, h.rho3d, h.rho2d);
  h.z = select(use3d, (tw0 * h.u + tw1 * h.v) + tw2, splat<V>(tw2));
  h.ex = exp_neg_lanes(S(-0.5) * rho);
  h.G = o * h.ex;
  const V amax = splat<V>(static_cast<S>(kAlphaMax));
  h.alpha = select(amax < h.G, amax, h.G);
}

// Whether a pixel row can hold a pixel where a surfel has alpha >= 1/255, so the forward skips the
// rows it cannot reach. alpha >= 1/255 needs rho <= B = 2 ln(255 o), i.e. rho3d <= B or rho2d <= B.
// With the intersection h = dx a + dy c + e (a = tv' x Tw, c = Tw x tu', e = tu' x tv' from the table
// rows), rho3d <= B is q(dx) = hx^2 + hy^2 - B hz^2 <= 0, a quadratic A2 dx^2 + 2 A1 dx + A0 in dx
// that has no root on the row when A2 > 0 and A1^2 < A2 A0; rho2d <= B needs dy^2 <= B/2. Computed
// in float64 with B raised by 1% + 0.01, far beyond the rounding of the per-pixel evaluation; rows
// are only skipped when the conic is a well-conditioned ellipse (A2 clearly positive).
struct RowCull {
  double a[3], c[3], e[3], B, A2;
  bool ellipse;
  template <typename S>
  explicit RowCull(const S* g) {
    const double tu[3] = {g[0], g[1], g[2]}, tv[3] = {g[3], g[4], g[5]}, tw[3] = {g[6], g[7], g[8]};
    cross3(tv, tw, a);
    cross3(tw, tu, c);
    cross3(tu, tv, e);
    const double o = g[11];
    B = o > 0 ? 2.0 * std::log(255.0 * o) * 1.01 + 0.01 : -1.0;
    A2 = a[0] * a[0] + a[1] * a[1] - B * a[2] * a[2];
    ellipse = A2 > 1e-3 * (a[0] * a[0] + a[1] * a[1] + std::fabs(B) * a[2] * a[2]);
  }
  // False when no pixel of the row at dy = y + 0.5 - c_y can be significant.
  bool reaches(double dy) const {
    if (B < 0) return false;
    if (!ellipse || dy * dy <= 0.5 * B) return true;
    const double f[3] = {dy * c[0] + e[0], dy * c[1] + e[1], dy * c[2] + e[2]};
    const double A1 = a[0] * f[0] + a[1] * f[1] - B * a[2] * f[2];
    const double A0 = f[0] * f[0] + f[1] * f[1] - B * f[2] * f[2];
    return A1 * A1 >= A2 * A0;
  }
};

// The (at most two) 8-pixel chunks of a box row inside a tile, starting at the box's left edge x0:
// whether each exists, the lanes inside [x0, x1), the lanes' offset from the tile's left edge and their
// pixel-centre x in the input dtype. A chunk may reach past the tile row; those lanes are masked and
// the per-pixel buffers are padded by kL.
template <typename S, typename Isa>
struct Chunks {
  bool on[2];
  int64_t off[2];
  typename Isa::M inbox[2];
  typename Lanes<S, Isa>::V xs[2];
};

template <typename S, typename Isa>
SG_INLINE void chunks(int64_t xa, int64_t x0, int64_t x1, Chunks<S, Isa>& cb) {
  using D = typename Isa::D;
  for (int h = 0; h < 2; ++h) {
    const int64_t b = x0 + kL * h;
    cb.on[h] = b < x1;
    cb.off[h] = b - xa;
    double xi[kL];
    S xc[kL];
    for (int k = 0; k < kL; ++k) {
      xi[k] = static_cast<double>(b + k);
      xc[k] = static_cast<S>(b + k) + S(0.5);
    }
    cb.inbox[h] = load<D>(xi) < static_cast<double>(x1);
    cb.xs[h] = load<typename Lanes<S, Isa>::V>(xc);
  }
}

// The work of one surfel in a tile is split into units, the 8-pixel chunks of its box rows. A first
// pass evaluates the geometry of every unit that still has live pixels (independent work the CPU can
// overlap) and keeps the units with significant lanes; a second pass composites those.
template <typename S, typename Isa>
struct ForwardUnit {
  typename Lanes<S, Isa>::V alpha;  // in the input dtype
  typename Isa::D alpha_d, z;
  typename Isa::M sig;
  int64_t i0;  // first pixel of the chunk in the tile
  int slot;    // row * 2 + chunk within the entry
};

template <typename S, typename Isa>
struct BackwardUnit {
  using V = typename Lanes<S, Isa>::V;
  Geo<S, Isa> g;
  typename Isa::M c;  // lanes where the surfel contributed
  decltype(std::declval<V>() < std::declval<V>()) cv;  // the same lanes as a mask of V
  int64_t i0;
  S dy, l0, l1, l2;
};

// Forward of one tile; the sink receives each pixel's results at the end.
template <typename S, typename Isa, typename Sink>
SG_INLINE int64_t forward_tile_impl(int64_t tile, const Kernel<S>& in, ForwardScratch& s, double* aux,
                                    int32_t* auxi, Sink& sink) {
  using L = Lanes<S, Isa>;
  using V = typename L::V;
  using D = typename Isa::D;
  using M = typename Isa::M;
  const Grid& grid = in.grid;
  const int64_t P = in.P;
  const int64_t tx = tile % grid.gx, ty = tile / grid.gx;
  const int64_t xa = tx * kTile, ya = ty * kTile;
  const int64_t xb = std::min(xa + kTile, grid.W), yb = std::min(ya + kTile, grid.H);
  const int64_t start = in.offsets[tile], end = in.offsets[tile + 1];
  std::fill(s.T, s.T + kPad, 1.0);
  for (double* v : {s.A, s.Dz, s.M1, s.M2, s.dist, s.z0, s.med}) std::fill(v, v + kPad, 0.0);
  std::fill(s.acc.begin(), s.acc.end(), 0.0);
  int64_t pairs = 0;
  std::fill(s.medi, s.medi + kPad, -1.0);
  for (int i = 0; i < kPad; ++i) s.alive[i] = (i < kTilePx && i / kTile < yb - ya && i % kTile < xb - xa) ? -1 : 0;
  int64_t n_alive = (xb - xa) * (yb - ya);
  std::fill(in.cmask + start * kSlots, in.cmask + end * kSlots, uint8_t(0));
  const D one = splat<D>(1.0), zero = splat<D>(0.0);
  const double near = static_cast<double>(in.near), amin = static_cast<double>(static_cast<S>(kAlphaMin));
  Chunks<S, Isa> cb;
  ForwardUnit<S, Isa> units[2 * kTile];
  for (int64_t j = start; j < end && n_alive > 0; ++j) {
    const int64_t r = in.lst[j];
    if (j + 1 < end) {  // the next surfel's rows are scattered in memory (depth order)
      const int64_t rn = in.lst[j + 1];
      __builtin_prefetch(in.tab + 12 * rn);
      __builtin_prefetch(in.boxes + 4 * rn);
      __builtin_prefetch(in.pay + P * rn);
    }
    int64_t x0, y0, x1, y1;
    if (!box_in_tile(in.boxes, r, tx, ty, x0, y0, x1, y1)) continue;
    const S* g = in.tab + 12 * r;
    const S* pr = in.pay + P * r;
    const S tv0 = g[3], tv1 = g[4], tv2 = g[5], tw0 = g[6], tw1 = g[7], tw2 = g[8], cy = g[10];
    chunks<S, Isa>(xa, x0, x1, cb);
    const RowCull cull(g);
    int n = 0;
    for (int64_t y = y0; y < y1; ++y) {
      const S dy = (static_cast<S>(y) + S(0.5)) - cy;
      if (!cull.reaches(static_cast<double>(dy))) continue;
      const S l0 = dy * tw0 - tv0, l1 = dy * tw1 - tv1, l2 = dy * tw2 - tv2;
      for (int h = 0; h < 2; ++h) {
        if (!cb.on[h]) continue;
        const int64_t i0 = (y - ya) * kTile + cb.off[h];
        const M act = load<M>(s.alive + i0) & cb.inbox[h];
        if (!any(act)) continue;
        Geo<S, Isa> gg;
        eval_lanes<S, Isa>(g, cb.xs[h], dy, l0, l1, l2, gg);
        ForwardUnit<S, Isa>& u = units[n];
        u.alpha = gg.alpha;
        u.alpha_d = L::to_d(gg.alpha);
        u.z = L::to_d(gg.z);
        u.sig = act & (L::to_d(gg.hz_raw) != 0.0) & (u.z >= near) & (u.alpha_d >= amin);
        u.i0 = i0;
        u.slot = static_cast<int>(2 * (y - y0) + h);
        n += any(u.sig);
      }
    }
    const D jd = splat<D>(static_cast<double>(j));
    for (int k = 0; k < n; ++k) {
      const ForwardUnit<S, Isa>& u = units[k];
      const int64_t i0 = u.i0;
      const D T = load<D>(s.T + i0);
      const D tn = T * (one - u.alpha_d);
      const M term = u.sig & (tn < kTMin);
      const int term_bits = lane_bits(term);
      if (term_bits != 0) {
        store(s.alive + i0, load<M>(s.alive + i0) & ~term);
        n_alive -= __builtin_popcount(term_bits);
      }
      const M c = u.sig & ~term;
      const int c_bits = lane_bits(c);
      in.cmask[j * kSlots + u.slot] = static_cast<uint8_t>(c_bits);
      pairs += __builtin_popcount(c_bits);
      const V Ts = L::from_d(T);
      const D w = select(c, L::to_d(u.alpha * Ts), zero);
      const D z = select(c, u.z, one);
      double* acc = s.acc.data() + i0;
      for (int64_t ch = 0; ch < P; ++ch)
        store(acc + ch * kPad, load<D>(acc + ch * kPad) + w * static_cast<double>(pr[ch]));
      const M mm = c & (T > 0.5);
      store(s.med + i0, select(mm, z, load<D>(s.med + i0)));
      store(s.medi + i0, select(mm, jd, load<D>(s.medi + i0)));
      const D inv_z = one / z;
      const D A = load<D>(s.A + i0), M1 = load<D>(s.M1 + i0), M2 = load<D>(s.M2 + i0);
      const D z0 = select(c & (A == 0.0), inv_z, load<D>(s.z0 + i0));  // A = 0 until the first contributor
      store(s.z0 + i0, z0);
      const D mt = in.cm * (z0 - inv_z);
      store(s.dist + i0, load<D>(s.dist + i0) + w * (mt * mt * A + M2 - 2.0 * mt * M1));
      store(s.A + i0, A + w);
      store(s.Dz + i0, load<D>(s.Dz + i0) + w * z);
      store(s.M1 + i0, M1 + w * mt);
      store(s.M2 + i0, M2 + w * mt * mt);
      store(s.T + i0, select(c, tn, T));
    }
  }
  double* ax = aux + tile * kAux * kPad;
  int c = 0;
  for (const double* v : {s.T, s.z0, s.A, s.M1, s.M2}) {
    std::copy(v, v + kTilePx, ax + c * kPad);
    std::fill(ax + c * kPad + kTilePx, ax + (c + 1) * kPad, 0.0);
    ++c;
  }
  int32_t* ai = auxi + tile * kAuxI * kTilePx;
  for (int i = 0; i < kTilePx; ++i) ai[i] = static_cast<int32_t>(s.medi[i]);
  for (int64_t y = ya; y < yb; ++y)
    for (int64_t x = xa; x < xb; ++x) sink.store(y * grid.W + x, (y - ya) * kTile + (x - xa), s);
  return pairs;
}

// Backward of one tile: the gradient sums of each list entry go where `out` says.
template <typename S, typename Isa>
SG_INLINE void backward_tile_impl(int64_t tile, const Kernel<S>& in, const double* aux, const int32_t* auxi,
                                  const double* gstat, const S* gpayv, BackwardScratch& s, const BackwardOut& out) {
  using L = Lanes<S, Isa>;
  using V = typename L::V;
  using D = typename Isa::D;
  using M = typename Isa::M;
  const Grid& grid = in.grid;
  const int64_t P = in.P, G = 12 + P;
  const int64_t tx = tile % grid.gx, ty = tile / grid.gx;
  const int64_t xa = tx * kTile, ya = ty * kTile;
  const int64_t start = in.offsets[tile];
  const double* ax = aux + tile * kAux * kPad;
  const int32_t* ai = auxi + tile * kAuxI * kTilePx;
  const double* gq = gstat + tile * 4 * kPad;
  double *Tb = s.T, *Bb = s.B, *medib = s.medi;
  const double *inv_z0 = ax + kPad, *Af = ax + 2 * kPad, *M1f = ax + 3 * kPad, *M2f = ax + 4 * kPad;
  const double *gA = gq, *gD = gA + kPad, *gM = gD + kPad, *gL = gM + kPad;
  const S* gpay = gpayv + tile * P * kPad;
  S* accs = reinterpret_cast<S*>(s.accp.data());  // (P, 8) lane sums of the payload gradients
  std::copy(ax, ax + kTilePx, Tb);
  std::fill(Bb, Bb + kTilePx, 0.0);
  for (int i = 0; i < kTilePx; ++i) medib[i] = ai[i];
  // one past the last entry that contributed anywhere in the tile
  int64_t hi = in.offsets[tile + 1];
  while (hi > start && !entry_contributed(in.cmask + (hi - 1) * kSlots)) --hi;
  const D one = splat<D>(1.0), zero = splat<D>(0.0);
  const double amax = static_cast<double>(static_cast<S>(kAlphaMax));
  const double cm = in.cm;
  double* acc = s.acc.data();
  Chunks<S, Isa> cb;
  BackwardUnit<S, Isa> units[2 * kTile];
  for (int64_t j = hi - 1; j >= start; --j) {
    const int64_t r = in.lst[j];
    if (j > start) {
      const int64_t rn = in.lst[j - 1];
      __builtin_prefetch(in.tab + 12 * rn);
      __builtin_prefetch(in.boxes + 4 * rn);
      __builtin_prefetch(in.pay + P * rn);
    }
    if (!entry_contributed(in.cmask + j * kSlots)) continue;
    int64_t x0, y0, x1, y1;
    box_in_tile(in.boxes, r, tx, ty, x0, y0, x1, y1);
    const S* g = in.tab + 12 * r;
    const S* pr = in.pay + P * r;
    const S tv0 = g[3], tv1 = g[4], tv2 = g[5], tw0s = g[6], tw1s = g[7], tw2s = g[8], cy = g[10];
    chunks<S, Isa>(xa, x0, x1, cb);
    const D jd = splat<D>(static_cast<double>(j));
    const uint8_t* cmj = in.cmask + j * kSlots;
    int n = 0;
    for (int64_t y = y0; y < y1; ++y) {
      const int row = static_cast<int>(y - y0);
      if ((cmj[2 * row] | cmj[2 * row + 1]) == 0) continue;
      const S dys = (static_cast<S>(y) + S(0.5)) - cy;
      const S l0s = dys * tw0s - tv0, l1s = dys * tw1s - tv1, l2s = dys * tw2s - tv2;
      for (int h = 0; h < 2; ++h) {
        const int bits = cmj[2 * row + h];
        if (bits == 0) continue;
        BackwardUnit<S, Isa>& u = units[n++];
        eval_lanes<S, Isa>(g, cb.xs[h], dys, l0s, l1s, l2s, u.g);
        u.c = load<M>(kLaneMasks.m[bits]);
        u.cv = load<decltype(u.cv)>(std::is_same<S, float>::value ? static_cast<const void*>(kLaneMasks.m32[bits])
                                                                  : static_cast<const void*>(kLaneMasks.m[bits]));
        u.i0 = (y - ya) * kTile + cb.off[h];
        u.dy = dys;
        u.l0 = l0s;
        u.l1 = l1s;
        u.l2 = l2s;
      }
    }
    if (n == 0) continue;
    std::fill(accs, accs + kL * P, S(0));  // the table sums live in registers
    // Per lane: the transmittance, compositing and distortion terms in float64, giving dL/dalpha and
    // dL/dz of the pair; from there on the chain through rho, z and the intersection runs in the input
    // dtype (as the packed backend's autograd does), summed per lane over the entry's pixels.
    const V vzero = splat<V>(S(0));
    V a0 = vzero, a1 = vzero, a2 = vzero, a3 = vzero, a4 = vzero, a5 = vzero, a6 = vzero, a7 = vzero, a8 = vzero,
      a9 = vzero, a10 = vzero;
    D a11 = zero;
    for (int k = 0; k < n; ++k) {
      const BackwardUnit<S, Isa>& u = units[k];
      const Geo<S, Isa>& gg = u.g;
      const M c = u.c;
      const int64_t i0 = u.i0;
      const S dy = u.dy, l0 = u.l0, l1 = u.l1, l2 = u.l2;
      const D alpha = L::to_d(gg.alpha);
      const D Tn = load<D>(Tb + i0);
      const D Tp = select(c, Tn / (one - alpha), Tn);
      store(Tb + i0, Tp);
      const V Tc = L::from_d(Tp);
      const D Tcd = L::to_d(Tc);
      const V wv = gg.alpha * Tc;
      const D w = L::to_d(wv);
      // payload: dL/dw = Σ_c gc pay_c and dL/dpay_c += w gc, in the input dtype
      V fd = vzero;
      for (int64_t ch = 0; ch < P; ++ch) {
        const V gc = load<V>(gpay + ch * kPad + i0);
        fd = fd + gc * pr[ch];
        store(accs + kL * ch, load<V>(accs + kL * ch) + select(u.cv, wv * gc, vzero));
      }
      const D fdot = L::to_d(fd);
      const D z = select(c, L::to_d(gg.z), one);
      const D inv_z = one / z;
      const D mt = cm * (load<D>(inv_z0 + i0) - inv_z);
      const D A = load<D>(Af + i0), M1 = load<D>(M1f + i0);
      const D gAv = load<D>(gA + i0), gDv = load<D>(gD + i0), gLv = load<D>(gL + i0);
      const D e = fdot + gAv + gDv * z + gLv * (mt * mt * A - 2.0 * mt * M1 + load<D>(M2f + i0));
      const D Bi = load<D>(Bb + i0);
      store(Bb + i0, select(c, alpha * e + (one - alpha) * Bi, Bi));
      const D g_ad = select(c & (L::to_d(gg.G) <= amax), Tcd * (e - Bi), zero);  // the clamp passes no gradient
      D g_zd = w * (gDv + gLv * 2.0 * (mt * A - M1) * cm * inv_z * inv_z);
      g_zd = select(load<D>(medib + i0) == jd, g_zd + load<D>(gM + i0), g_zd);
      g_zd = select(c, g_zd, zero);
      a11 = a11 + g_ad * L::to_d(gg.ex);
      const V g_a = L::from_d(g_ad), g_z = L::from_d(g_zd);
      const V g_rho = S(-0.5) * g_a * gg.G;
      // 3D branch: rho = u^2 + v^2, z = Tw.(u, v, 1), (u, v) = (h_x, h_y) / h_z with h = k x l;
      // low-pass branch: rho = 2 (dx^2 + dy^2), z = Tw[2]
      const auto u3 = (gg.hz_raw != S(0)) & (gg.rho3d <= gg.rho2d);
      const V uu = select(u3, gg.u, vzero), vv = select(u3, gg.v, vzero);
      const V inv_hz = select(u3, S(1) / gg.hz, vzero);
      const V g_z3 = select(u3, g_z, vzero);
      const V g_rho2 = select(u3, vzero, S(4) * g_rho);
      const V g_u = S(2) * g_rho * uu + g_z3 * tw0s;
      const V g_v = S(2) * g_rho * vv + g_z3 * tw1s;
      const V g_hx = g_u * inv_hz, g_hy = g_v * inv_hz, g_hz = -(g_u * uu + g_v * vv) * inv_hz;
      const V g_k0 = l1 * g_hz - l2 * g_hy;
      const V g_k1 = l2 * g_hx - l0 * g_hz;
      const V g_k2 = l0 * g_hy - l1 * g_hx;
      const V g_l0 = g_hy * gg.k2 - g_hz * gg.k1;
      const V g_l1 = g_hz * gg.k0 - g_hx * gg.k2;
      const V g_l2 = g_hx * gg.k1 - g_hy * gg.k0;
      a0 = a0 - g_k0;
      a1 = a1 - g_k1;
      a2 = a2 - g_k2;
      a3 = a3 - g_l0;
      a4 = a4 - g_l1;
      a5 = a5 - g_l2;
      a6 = a6 + (gg.dx * g_k0 + dy * g_l0 + g_z3 * uu);
      a7 = a7 + (gg.dx * g_k1 + dy * g_l1 + g_z3 * vv);
      a8 = a8 + (gg.dx * g_k2 + dy * g_l2 + g_z);
      a9 = a9 - (g_k0 * tw0s + g_k1 * tw1s + g_k2 * tw2s + g_rho2 * gg.dx);
      a10 = a10 - (g_l0 * tw0s + g_l1 * tw1s + g_l2 * tw2s + g_rho2 * dy);
    }
    const V rows[11] = {a0, a1, a2, a3, a4, a5, a6, a7, a8, a9, a10};
    for (int k = 0; k < 11; ++k) store(acc + kL * k, L::to_d(rows[k]));
    store(acc + kL * 11, a11);
    for (int64_t ch = 0; ch < P; ++ch) store(acc + kL * (12 + ch), L::to_d(load<V>(accs + kL * ch)));
    if (out.total != nullptr) {
      double* dst = out.total + G * r;
      for (int64_t k = 0; k < G; ++k) {
        const double* a = acc + kL * k;
        dst[k] += ((((((a[0] + a[1]) + a[2]) + a[3]) + a[4]) + a[5]) + a[6]) + a[7];
      }
    } else {
      double* dst = out.gbuf + G * j;
      for (int64_t k = 0; k < G; ++k) {
        const double* a = acc + kL * k;
        dst[k] = ((((((a[0] + a[1]) + a[2]) + a[3]) + a[4]) + a[5]) + a[6]) + a[7];
      }
      out.touched[j] = 1;
    }
  }
}

// Entry points of this build of the tile loops.
template <typename S, typename Sink>
__attribute__((noinline)) int64_t forward_tile(int64_t t, const Kernel<S>& in, ForwardScratch& s, double* aux,
                                               int32_t* auxi, Sink& sink) {
  return forward_tile_impl<S, SG_SURFELS_ISA, Sink>(t, in, s, aux, auxi, sink);
}
template <typename S>
__attribute__((noinline)) void backward_tile(int64_t t, const Kernel<S>& in, const double* aux, const int32_t* auxi,
                                             const double* gstat, const S* gpay, BackwardScratch& s,
                                             const BackwardOut& out) {
  backward_tile_impl<S, SG_SURFELS_ISA>(t, in, aux, auxi, gstat, gpay, s, out);
}

#endif  // SG_SURFELS_KERNEL_BODY
