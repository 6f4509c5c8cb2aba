// Native CPU compositing of 2D Gaussian surfels: the backend="cpp" path of rasterize_surfels.
//
// Same inputs and rules as the packed torch backend (sage_core/render/_packed.py) and the Triton
// tile kernels (_triton_surfels.py), see docs/rendering.md:
//   * binning: every surfel is listed in each 16x16 tile its candidate pixel box touches, in the
//     given (centre-depth) order;
//   * forward: one tile at a time, each surfel of the tile's list visits the pixels of its box inside
//     the tile; alpha = min(0.99, o*exp(-rho/2)) with the low-pass rho = min(rho3d, rho2d); a pair is
//     skipped when h_z = 0, z < near or alpha < 1/255; a pixel stops before the first surfel with
//     T*(1 - alpha) < 1e-4. T is carried in float64; feature, alpha, depth and distortion sums are
//     accumulated in float64 and rounded to the input dtype at the end;
//   * backward: per tile, back to front from each pixel's last contributor, recomputing the
//     intersection and recovering T by division. Each (tile, surfel) entry writes its gradient sum
//     to its own slot; the slots are reduced per surfel in list order afterwards, so the result is
//     race-free and independent of the thread count and schedule.
// Per-pair arithmetic is done in the input dtype in the packed backend's operation order (the
// build disables FMA contraction), so the threshold decisions match it.
// Tiles are processed by OpenMP threads (dynamic schedule), as many as at::get_num_threads().

#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/empty_like.h>
#include <ATen/ops/zeros.h>
#include <ATen/ops/_to_copy.h>
#include <c10/util/Exception.h>
#include <torch/library.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

#ifdef _OPENMP
#include <omp.h>
#endif

namespace {

constexpr int kTile = 16;
constexpr int kTilePx = kTile * kTile;
constexpr double kAlphaMax = 0.99;
constexpr double kAlphaMin = 1.0 / 255.0;
constexpr double kTMin = 1e-4;
// images smaller than this run their per-pixel loops on one thread (waking threads costs more)
constexpr int64_t kParallelPixels = 1 << 14;

// Ray-splat intersection, low-pass filter and alpha of one surfel at one pixel centre (eval_pairs).
template <typename S>
struct Hit {
  S dx, dy, k0, k1, k2, l0, l1, l2, hz, u, v, ex, G, alpha, z;
  bool use3d, sig;
};

template <typename S>
inline void intersect(const S* g, S px, S py, S near, Hit<S>& h) {
  const S tu0 = g[0], tu1 = g[1], tu2 = g[2], tv0 = g[3], tv1 = g[4], tv2 = g[5];
  const S tw0 = g[6], tw1 = g[7], tw2 = g[8], cx = g[9], cy = g[10], o = g[11];
  h.dx = px - cx;
  h.dy = py - cy;
  h.k0 = h.dx * tw0 - tu0;
  h.k1 = h.dx * tw1 - tu1;
  h.k2 = h.dx * tw2 - tu2;
  h.l0 = h.dy * tw0 - tv0;
  h.l1 = h.dy * tw1 - tv1;
  h.l2 = h.dy * tw2 - tv2;
  const S hx = h.k1 * h.l2 - h.k2 * h.l1;
  const S hy = h.k2 * h.l0 - h.k0 * h.l2;
  const S hz = h.k0 * h.l1 - h.k1 * h.l0;
  const bool hz_ok = hz != S(0);
  h.hz = hz_ok ? hz : S(1);
  h.u = hx / h.hz;
  h.v = hy / h.hz;
  const S rho2d = S(2) * (h.dx * h.dx + h.dy * h.dy);
  const S rho3d = h.u * h.u + h.v * h.v;
  h.use3d = hz_ok && (rho3d <= rho2d);
  const S rho = h.use3d ? rho3d : rho2d;
  h.z = h.use3d ? (tw0 * h.u + tw1 * h.v) + tw2 : tw2;
  h.ex = std::exp(S(-0.5) * rho);
  h.G = o * h.ex;
  h.alpha = std::min(h.G, S(kAlphaMax));
  h.sig = hz_ok && (h.z >= near) && (h.alpha >= S(kAlphaMin));
}

// Cheap pre-pass over one row of a surfel's box inside a tile, x in [x0, x0 + n), n <= 16: finds
// the pixels that may be significant, i.e. h_z != 0, z >= near and rho <= rho_max, where rho_max
// bounds the rho with alpha >= 1/255 (2 ln(255 o) plus a margin far above the rounding of exp).
// It computes rho and z exactly as `intersect` (same operations in the same order) for all 16
// lanes without branches or exp, so the compiler vectorizes it; it writes the candidates' offsets
// to idx and their rho and z to rho_out and z_out (indexed by offset) and returns their count.
template <typename S>
inline int row_candidates(const S* g, int64_t x0, int64_t n, S py, S near, S rho_max, int32_t* idx, S* rho_out,
                          S* z_out) {
  const S tu0 = g[0], tu1 = g[1], tu2 = g[2], tv0 = g[3], tv1 = g[4], tv2 = g[5];
  const S tw0 = g[6], tw1 = g[7], tw2 = g[8], cx = g[9], cy = g[10];
  const S dy = py - cy;
  const S l0 = dy * tw0 - tv0, l1 = dy * tw1 - tv1, l2 = dy * tw2 - tv2;
  const S rdy = dy * dy;
  S keep[kTile];
  const int xi0 = static_cast<int>(x0), ni = static_cast<int>(n);
  for (int k = 0; k < kTile; ++k) {
    const S dx = (static_cast<S>(xi0 + k) + S(0.5)) - cx;
    const S k0 = dx * tw0 - tu0, k1 = dx * tw1 - tu1, k2 = dx * tw2 - tu2;
    const S hx = k1 * l2 - k2 * l1;
    const S hy = k2 * l0 - k0 * l2;
    const S hz = k0 * l1 - k1 * l0;
    const S hzs = hz != S(0) ? hz : S(1);
    const S u = hx / hzs, v = hy / hzs;
    const S rho2d = S(2) * (dx * dx + rdy);
    const S rho3d = u * u + v * v;
    const S z3 = (tw0 * u + tw1 * v) + tw2;
    // written as selects on floating-point compares only, which the vectorizer accepts
    const S rho_s = rho3d <= rho2d ? rho3d : rho2d;
    const S rho = hz != S(0) ? rho_s : rho2d;
    const S z_s = rho3d <= rho2d ? z3 : tw2;
    const S z = hz != S(0) ? z_s : tw2;
    const S a = z >= near ? S(1) : S(0);
    const S b = rho <= rho_max ? a : S(0);
    keep[k] = hz != S(0) ? b : S(0);
    rho_out[k] = rho;
    z_out[k] = z;
  }
  int m = 0;
  for (int k = 0; k < ni; ++k) {
    idx[m] = k;
    m += keep[k] != S(0);
  }
  return m;
}

// rho_max of row_candidates for opacity o (alpha < 1/255 everywhere when o < 1/255).
template <typename S>
inline S rho_bound(S o) {
  const double b = 2.0 * std::log(255.0 * static_cast<double>(o));
  return static_cast<S>(b + 1e-3 + 1e-4 * std::fabs(b));
}

struct Grid {
  int64_t W, H, gx, gy;
  int64_t tiles() const { return gx * gy; }
};

// The pixel box of surfel r clipped to tile t: [x0, x1) x [y0, y1); false when empty.
inline bool box_in_tile(const int64_t* boxes, int64_t r, int64_t tx, int64_t ty, int64_t& x0, int64_t& y0,
                        int64_t& x1, int64_t& y1) {
  const int64_t* b = boxes + 4 * r;
  x0 = std::max(b[0], tx * kTile);
  y0 = std::max(b[1], ty * kTile);
  x1 = std::min(b[2], tx * kTile + kTile);
  y1 = std::min(b[3], ty * kTile + kTile);
  return x1 > x0 && y1 > y0;
}

int num_threads() { return std::max(1, at::get_num_threads()); }

// Per-tile lists of surfel indices (ascending within a tile) from candidate pixel boxes (Nv, 4).
std::vector<at::Tensor> bin_tiles_impl(const at::Tensor& boxes_t, const Grid& grid) {
  const int64_t nv = boxes_t.size(0);
  const int64_t* boxes = boxes_t.data_ptr<int64_t>();
  const int64_t nt = grid.tiles();
  at::Tensor offsets_t = at::zeros({nt + 1}, boxes_t.options());
  int64_t* offsets = offsets_t.data_ptr<int64_t>();
  for (int64_t r = 0; r < nv; ++r) {
    const int64_t* b = boxes + 4 * r;
    if (b[2] <= b[0] || b[3] <= b[1]) continue;
    const int64_t tx0 = b[0] / kTile, ty0 = b[1] / kTile, tx1 = (b[2] - 1) / kTile + 1, ty1 = (b[3] - 1) / kTile + 1;
    for (int64_t ty = ty0; ty < ty1; ++ty)
      for (int64_t tx = tx0; tx < tx1; ++tx) offsets[ty * grid.gx + tx + 1] += 1;
  }
  for (int64_t t = 0; t < nt; ++t) offsets[t + 1] += offsets[t];
  at::Tensor lst_t = at::empty({offsets[nt]}, boxes_t.options().dtype(at::kInt));
  int32_t* lst = lst_t.data_ptr<int32_t>();
  std::vector<int64_t> fill(offsets, offsets + nt);
  for (int64_t r = 0; r < nv; ++r) {
    const int64_t* b = boxes + 4 * r;
    if (b[2] <= b[0] || b[3] <= b[1]) continue;
    const int64_t tx0 = b[0] / kTile, ty0 = b[1] / kTile, tx1 = (b[2] - 1) / kTile + 1, ty1 = (b[3] - 1) / kTile + 1;
    for (int64_t ty = ty0; ty < ty1; ++ty)
      for (int64_t tx = tx0; tx < tx1; ++tx) lst[fill[ty * grid.gx + tx]++] = static_cast<int32_t>(r);
  }
  return {offsets_t, lst_t};
}

// Forward of one tile. Per-pixel outputs: pay_out (HW, P), stats (HW, 4) = (A, sum w z, median,
// distortion); aux (HW, 5) float64 = (T final, 1/z0, A, M1, M2); auxi (HW, 3) int32 = (last list
// index + 1, median list index or -1, contributor count).
template <typename S>
struct ForwardScratch {
  std::vector<double> T, acc, A, Dz, M1, M2, dist, z0, med;
  std::vector<int32_t> last, medi, cnt;
  std::vector<unsigned char> alive;
  explicit ForwardScratch(int64_t P)
      : T(kTilePx), acc(kTilePx * P), A(kTilePx), Dz(kTilePx), M1(kTilePx), M2(kTilePx), dist(kTilePx),
        z0(kTilePx), med(kTilePx), last(kTilePx), medi(kTilePx), cnt(kTilePx), alive(kTilePx) {}
};

template <typename S>
void forward_tile(int64_t tile, const Grid& grid, const S* tab, const S* pay, int64_t P, const int64_t* boxes,
                  const int64_t* offsets, const int32_t* lst, S near, double cm, ForwardScratch<S>& s, S* pay_out,
                  S* stats, double* aux, int32_t* auxi) {
  const int64_t tx = tile % grid.gx, ty = tile / grid.gx;
  const int64_t xa = tx * kTile, ya = ty * kTile;
  const int64_t xb = std::min(xa + kTile, grid.W), yb = std::min(ya + kTile, grid.H);
  const int64_t start = offsets[tile], end = offsets[tile + 1];
  std::fill(s.T.begin(), s.T.end(), 1.0);
  std::fill(s.acc.begin(), s.acc.end(), 0.0);
  for (auto* v : {&s.A, &s.Dz, &s.M1, &s.M2, &s.dist, &s.z0, &s.med}) std::fill(v->begin(), v->end(), 0.0);
  std::fill(s.last.begin(), s.last.end(), static_cast<int32_t>(start));
  std::fill(s.medi.begin(), s.medi.end(), -1);
  std::fill(s.cnt.begin(), s.cnt.end(), 0);
  std::fill(s.alive.begin(), s.alive.end(), 1);
  int64_t n_alive = (xb - xa) * (yb - ya);
  for (int64_t j = start; j < end && n_alive > 0; ++j) {
    const int64_t r = lst[j];
    if (j + 1 < end) {  // the next surfel's rows are scattered in memory (depth order)
      const int64_t rn = lst[j + 1];
      __builtin_prefetch(tab + 12 * rn);
      __builtin_prefetch(boxes + 4 * rn);
      __builtin_prefetch(pay + P * rn);
    }
    int64_t x0, y0, x1, y1;
    if (!box_in_tile(boxes, r, tx, ty, x0, y0, x1, y1)) continue;
    const S* g = tab + 12 * r;
    const S* pr = pay + P * r;
    const S rho_max = rho_bound(g[11]);
    const S o = g[11];
    int32_t cand[kTile];
    S rho_r[kTile], z_r[kTile];
    for (int64_t y = y0; y < y1; ++y) {
      const S py = static_cast<S>(y) + S(0.5);
      const int nc = row_candidates(g, x0, x1 - x0, py, near, rho_max, cand, rho_r, z_r);
      for (int c_i = 0; c_i < nc; ++c_i) {
        const int k = cand[c_i];
        const int64_t x = x0 + k;
        const int64_t i = (y - ya) * kTile + (x - xa);
        if (!s.alive[i]) continue;
        // alpha exactly as `intersect` computes it from rho
        const S alpha = std::min(o * std::exp(S(-0.5) * rho_r[k]), S(kAlphaMax));
        if (!(alpha >= S(kAlphaMin))) continue;
        const double T = s.T[i];
        const double t_next = T * (1.0 - static_cast<double>(alpha));
        if (t_next < kTMin) {
          s.alive[i] = 0;
          --n_alive;
          continue;
        }
        const double w = static_cast<double>(alpha * static_cast<S>(T));
        const double z = static_cast<double>(z_r[k]);
        double* acc = &s.acc[i * P];
        for (int64_t c = 0; c < P; ++c) acc[c] += w * static_cast<double>(pr[c]);
        if (T > 0.5) {
          s.med[i] = z;
          s.medi[i] = static_cast<int32_t>(j);
        }
        const double inv_z = 1.0 / z;
        if (s.cnt[i] == 0) s.z0[i] = inv_z;  // 1 / depth of the pixel's first contributor
        const double mt = cm * (s.z0[i] - inv_z);  // m(z) - m(z0), m(z) = far/(far - near)(1 - near/z)
        s.dist[i] += w * (mt * mt * s.A[i] + s.M2[i] - 2.0 * mt * s.M1[i]);
        s.A[i] += w;
        s.Dz[i] += w * z;
        s.M1[i] += w * mt;
        s.M2[i] += w * mt * mt;
        s.T[i] = t_next;
        s.last[i] = static_cast<int32_t>(j + 1);
        s.cnt[i] += 1;
      }
    }
  }
  for (int64_t y = ya; y < yb; ++y) {
    for (int64_t x = xa; x < xb; ++x) {
      const int64_t i = (y - ya) * kTile + (x - xa);
      const int64_t p = y * grid.W + x;
      for (int64_t c = 0; c < P; ++c) pay_out[p * P + c] = static_cast<S>(s.acc[i * P + c]);
      S* st = stats + 4 * p;
      st[0] = static_cast<S>(s.A[i]);
      st[1] = static_cast<S>(s.Dz[i]);
      st[2] = static_cast<S>(s.med[i]);
      st[3] = static_cast<S>(s.dist[i]);
      double* ax = aux + 5 * p;
      ax[0] = s.T[i];
      ax[1] = s.z0[i];
      ax[2] = s.A[i];
      ax[3] = s.M1[i];
      ax[4] = s.M2[i];
      int32_t* ai = auxi + 3 * p;
      ai[0] = s.last[i];
      ai[1] = s.medi[i];
      ai[2] = s.cnt[i];
    }
  }
}

void check_inputs(const at::Tensor& table, const at::Tensor& payload, const at::Tensor& boxes) {
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
void forward_all(const at::Tensor& table, const at::Tensor& payload, const at::Tensor& boxes, const at::Tensor& offsets,
                 const at::Tensor& lst, const Grid& grid, double near, double cm, at::Tensor& pay_out, at::Tensor& stats,
                 at::Tensor& aux, at::Tensor& auxi) {
  const int64_t P = payload.size(1);
  const S* tab = table.data_ptr<S>();
  const S* pay = payload.data_ptr<S>();
  const int64_t* bx = boxes.data_ptr<int64_t>();
  const int64_t* off = offsets.data_ptr<int64_t>();
  const int32_t* ls = lst.data_ptr<int32_t>();
  S* po = pay_out.data_ptr<S>();
  S* st = stats.data_ptr<S>();
  double* ax = aux.data_ptr<double>();
  int32_t* ai = auxi.data_ptr<int32_t>();
  const int64_t nt = grid.tiles();
  const S nr = static_cast<S>(near);
#pragma omp parallel num_threads(num_threads()) if (nt > 1)
  {
    ForwardScratch<S> scratch(P);
#pragma omp for schedule(dynamic, 1)
    for (int64_t t = 0; t < nt; ++t) forward_tile<S>(t, grid, tab, pay, P, bx, off, ls, nr, cm, scratch, po, st, ax, ai);
  }
}

// table (Nv, 12), payload (Nv, P), boxes (Nv, 4) int64 -> [pay_out (HW, P), stats (HW, 4), aux (HW, 5) f64,
// auxi (HW, 3) i32, offsets (tiles + 1) i64, lst (L,) i32].
std::vector<at::Tensor> composite_forward(const at::Tensor& table, const at::Tensor& payload, const at::Tensor& boxes,
                                          int64_t width, int64_t height, double near, double far) {
  check_inputs(table, payload, boxes);
  TORCH_CHECK(width > 0 && height > 0, "surfels_cpu: image size must be positive");
  const Grid grid{width, height, (width + kTile - 1) / kTile, (height + kTile - 1) / kTile};
  const int64_t HW = width * height, P = payload.size(1);
  auto bins = bin_tiles_impl(boxes, grid);
  at::Tensor pay_out = at::empty({HW, P}, table.options());
  at::Tensor stats = at::empty({HW, 4}, table.options());
  at::Tensor aux = at::empty({HW, 5}, table.options().dtype(at::kDouble));
  at::Tensor auxi = at::empty({HW, 3}, table.options().dtype(at::kInt));
  const double cm = far * near / (far - near);
  if (table.scalar_type() == at::kFloat)
    forward_all<float>(table, payload, boxes, bins[0], bins[1], grid, near, cm, pay_out, stats, aux, auxi);
  else
    forward_all<double>(table, payload, boxes, bins[0], bins[1], grid, near, cm, pay_out, stats, aux, auxi);
  return {pay_out, stats, aux, auxi, bins[0], bins[1]};
}

struct BackwardScratch {
  std::vector<double> T, B, gsum;
  explicit BackwardScratch(int64_t P) : T(kTilePx), B(kTilePx), gsum(12 + P) {}
};

// Backward of one tile: writes the gradient sums of list entry j (12 table rows, then P payload
// channels) to gbuf[j] and marks it in touched[j].
template <typename S>
void backward_tile(int64_t tile, const Grid& grid, const S* tab, const S* pay, int64_t P, const int64_t* boxes,
                   const int64_t* offsets, const int32_t* lst, S near, double cm, const double* aux,
                   const int32_t* auxi, const S* g_pay, const S* g_s, BackwardScratch& s, double* gbuf,
                   unsigned char* touched) {
  const int64_t tx = tile % grid.gx, ty = tile / grid.gx;
  const int64_t xa = tx * kTile, ya = ty * kTile;
  const int64_t xb = std::min(xa + kTile, grid.W), yb = std::min(ya + kTile, grid.H);
  const int64_t start = offsets[tile];
  int64_t hi = start;
  for (int64_t y = ya; y < yb; ++y) {
    for (int64_t x = xa; x < xb; ++x) {
      const int64_t i = (y - ya) * kTile + (x - xa), p = y * grid.W + x;
      s.T[i] = aux[5 * p];
      s.B[i] = 0.0;
      hi = std::max<int64_t>(hi, auxi[3 * p]);
    }
  }
  const int64_t G = 12 + P;
  Hit<S> h;
  for (int64_t j = hi - 1; j >= start; --j) {
    const int64_t r = lst[j];
    if (j > start) {
      const int64_t rn = lst[j - 1];
      __builtin_prefetch(tab + 12 * rn);
      __builtin_prefetch(boxes + 4 * rn);
      __builtin_prefetch(pay + P * rn);
    }
    int64_t x0, y0, x1, y1;
    if (!box_in_tile(boxes, r, tx, ty, x0, y0, x1, y1)) continue;
    const S* g = tab + 12 * r;
    const S* pr = pay + P * r;
    const double tw0 = g[6], tw1 = g[7], tw2 = g[8];
    double* accp = s.gsum.data() + 12;  // payload channels
    std::fill(accp, accp + P, 0.0);
    // table-row gradient sums, kept in registers
    double a0 = 0, a1 = 0, a2 = 0, a3 = 0, a4 = 0, a5 = 0, a6 = 0, a7 = 0, a8 = 0, a9 = 0, a10 = 0, a11 = 0;
    bool any = false;
    const S rho_max = rho_bound(g[11]);
    int32_t cand[kTile];
    S rho_r[kTile], z_r[kTile];
    for (int64_t y = y0; y < y1; ++y) {
      const S py = static_cast<S>(y) + S(0.5);
      const int nc = row_candidates(g, x0, x1 - x0, py, near, rho_max, cand, rho_r, z_r);
      for (int c_i = 0; c_i < nc; ++c_i) {
        const int64_t x = x0 + cand[c_i];
        const int64_t p = y * grid.W + x;
        const int32_t* ai = auxi + 3 * p;
        if (j >= ai[0]) continue;
        intersect(g, static_cast<S>(x) + S(0.5), py, near, h);
        if (!h.sig) continue;
        any = true;
        const int64_t i = (y - ya) * kTile + (x - xa);
        const double alpha = h.alpha;
        const double T = s.T[i] / (1.0 - alpha);
        s.T[i] = T;
        const S Tc = static_cast<S>(T);
        const double w = static_cast<double>(h.alpha * Tc);
        const S* gp = g_pay + P * p;
        double fdot = 0.0;
        for (int64_t c = 0; c < P; ++c) {
          const double gc = static_cast<double>(gp[c]);
          fdot += gc * static_cast<double>(pr[c]);
          accp[c] += w * gc;
        }
        const double* ax = aux + 5 * p;
        const S* gs = g_s + 4 * p;
        const double gA = gs[0], gD = gs[1], gM = gs[2], gL = gs[3];
        const double z = h.z, inv_z0 = ax[1], Af = ax[2], M1f = ax[3], M2f = ax[4];
        const double inv_z = 1.0 / z;
        const double mt = cm * (inv_z0 - inv_z);
        const double e = fdot + gA + gD * z + gL * (mt * mt * Af - 2.0 * mt * M1f + M2f);
        const double Bi = s.B[i];
        double g_a = static_cast<double>(Tc) * (e - Bi);
        s.B[i] = alpha * e + (1.0 - alpha) * Bi;
        double g_z = w * (gD + gL * 2.0 * (mt * Af - M1f) * cm * inv_z * inv_z);
        if (ai[1] == j) g_z += gM;
        if (!(h.G <= S(kAlphaMax))) g_a = 0.0;  // the clamp passes no gradient
        a11 += g_a * static_cast<double>(h.ex);
        const double g_rho = -0.5 * g_a * static_cast<double>(h.G);
        const double dx = h.dx, dy = h.dy;
        if (h.use3d) {
          // rho = u^2 + v^2, z = Tw.(u, v, 1), (u, v) = (h_x, h_y) / h_z with h = k x l
          const double u = h.u, v = h.v, inv_hz = 1.0 / static_cast<double>(h.hz);
          const double k0 = h.k0, k1 = h.k1, k2 = h.k2, l0 = h.l0, l1 = h.l1, l2 = h.l2;
          const double g_u = 2.0 * g_rho * u + g_z * tw0;
          const double g_v = 2.0 * g_rho * v + g_z * tw1;
          const double g_hx = g_u * inv_hz, g_hy = g_v * inv_hz, g_hz = -(g_u * u + g_v * v) * inv_hz;
          const double g_k0 = l1 * g_hz - l2 * g_hy;
          const double g_k1 = l2 * g_hx - l0 * g_hz;
          const double g_k2 = l0 * g_hy - l1 * g_hx;
          const double g_l0 = g_hy * k2 - g_hz * k1;
          const double g_l1 = g_hz * k0 - g_hx * k2;
          const double g_l2 = g_hx * k1 - g_hy * k0;
          a0 -= g_k0;
          a1 -= g_k1;
          a2 -= g_k2;
          a3 -= g_l0;
          a4 -= g_l1;
          a5 -= g_l2;
          a6 += dx * g_k0 + dy * g_l0 + g_z * u;
          a7 += dx * g_k1 + dy * g_l1 + g_z * v;
          a8 += dx * g_k2 + dy * g_l2 + g_z;
          a9 -= g_k0 * tw0 + g_k1 * tw1 + g_k2 * tw2;
          a10 -= g_l0 * tw0 + g_l1 * tw1 + g_l2 * tw2;
        } else {
          // low-pass branch: rho = 2(dx^2 + dy^2), z = Tw[2]
          const double g_rho2 = 4.0 * g_rho;
          a8 += g_z;
          a9 -= g_rho2 * dx;
          a10 -= g_rho2 * dy;
        }
      }
    }
    if (any) {
      double* dst = gbuf + G * j;
      const double rows[12] = {a0, a1, a2, a3, a4, a5, a6, a7, a8, a9, a10, a11};
      std::copy(rows, rows + 12, dst);
      std::copy(accp, accp + P, dst + 12);
      touched[j] = 1;
    }
  }
}

template <typename S>
void backward_all(const at::Tensor& table, const at::Tensor& payload, const at::Tensor& boxes, const at::Tensor& offsets,
                  const at::Tensor& lst, const at::Tensor& aux, const at::Tensor& auxi, const at::Tensor& g_pay,
                  const at::Tensor& g_s, const Grid& grid, double near, double cm, at::Tensor& gtab, at::Tensor& gpay) {
  const int64_t P = payload.size(1), G = 12 + P, L = lst.size(0), nt = grid.tiles();
  const S* tab = table.data_ptr<S>();
  const S* pay = payload.data_ptr<S>();
  const int64_t* bx = boxes.data_ptr<int64_t>();
  const int64_t* off = offsets.data_ptr<int64_t>();
  const int32_t* ls = lst.data_ptr<int32_t>();
  const double* ax = aux.data_ptr<double>();
  const int32_t* ai = auxi.data_ptr<int32_t>();
  const S* gp = g_pay.data_ptr<S>();
  const S* gs = g_s.data_ptr<S>();
  std::vector<double> gbuf(static_cast<size_t>(L * G));
  std::vector<unsigned char> touched(static_cast<size_t>(L), 0);
  const S nr = static_cast<S>(near);
#pragma omp parallel num_threads(num_threads()) if (nt > 1)
  {
    BackwardScratch scratch(P);
#pragma omp for schedule(dynamic, 1)
    for (int64_t t = 0; t < nt; ++t)
      backward_tile<S>(t, grid, tab, pay, P, bx, off, ls, nr, cm, ax, ai, gp, gs, scratch, gbuf.data(), touched.data());
  }
  // deterministic reduction of the per-entry sums, in list order
  const int64_t nv = table.size(0);
  std::vector<double> total(static_cast<size_t>(nv * G), 0.0);
  for (int64_t j = 0; j < L; ++j) {
    if (!touched[j]) continue;
    double* dst = total.data() + G * ls[j];
    const double* src = gbuf.data() + G * j;
    for (int64_t c = 0; c < G; ++c) dst[c] += src[c];
  }
  S* gt = gtab.data_ptr<S>();
  S* gq = gpay.data_ptr<S>();
  for (int64_t r = 0; r < nv; ++r) {
    for (int64_t c = 0; c < 12; ++c) gt[12 * r + c] = static_cast<S>(total[G * r + c]);
    for (int64_t c = 0; c < P; ++c) gq[P * r + c] = static_cast<S>(total[G * r + 12 + c]);
  }
}

// Gradients of the table (Nv, 12) and payload (Nv, P) from the output gradients g_pay (HW, P) and
// g_stats (HW, 4) (A, sum w z, median, distortion).
std::vector<at::Tensor> composite_backward(const at::Tensor& table, const at::Tensor& payload, const at::Tensor& boxes,
                                           const at::Tensor& offsets, const at::Tensor& lst, const at::Tensor& aux,
                                           const at::Tensor& auxi, const at::Tensor& g_pay, const at::Tensor& g_stats,
                                           int64_t width, int64_t height, double near, double far) {
  check_inputs(table, payload, boxes);
  const int64_t HW = width * height, P = payload.size(1);
  TORCH_CHECK(g_pay.sizes() == at::IntArrayRef({HW, P}) && g_pay.is_contiguous() &&
                  g_pay.scalar_type() == table.scalar_type(),
              "surfels_cpu: g_pay must be a contiguous (HW, P) tensor of the table's dtype");
  TORCH_CHECK(g_stats.sizes() == at::IntArrayRef({HW, 4}) && g_stats.is_contiguous() &&
                  g_stats.scalar_type() == table.scalar_type(),
              "surfels_cpu: g_stats must be a contiguous (HW, 4) tensor of the table's dtype");
  TORCH_CHECK(aux.sizes() == at::IntArrayRef({HW, 5}) && aux.scalar_type() == at::kDouble &&
                  auxi.sizes() == at::IntArrayRef({HW, 3}) && auxi.scalar_type() == at::kInt,
              "surfels_cpu: aux buffers do not match the image size");
  const Grid grid{width, height, (width + kTile - 1) / kTile, (height + kTile - 1) / kTile};
  TORCH_CHECK(offsets.numel() == grid.tiles() + 1 && offsets.scalar_type() == at::kLong &&
                  lst.scalar_type() == at::kInt,
              "surfels_cpu: tile lists do not match the image size");
  at::Tensor gtab = at::empty_like(table);
  at::Tensor gpay = at::empty_like(payload);
  const double cm = far * near / (far - near);
  if (table.scalar_type() == at::kFloat)
    backward_all<float>(table, payload, boxes, offsets, lst, aux, auxi, g_pay, g_stats, grid, near, cm, gtab, gpay);
  else
    backward_all<double>(table, payload, boxes, offsets, lst, aux, auxi, g_pay, g_stats, grid, near, cm, gtab, gpay);
  return {gtab, gpay};
}

std::vector<at::Tensor> bin_tiles(const at::Tensor& boxes, int64_t width, int64_t height) {
  TORCH_CHECK(boxes.dim() == 2 && boxes.size(1) == 4 && boxes.is_contiguous() && boxes.scalar_type() == at::kLong &&
                  boxes.device().is_cpu(),
              "surfels_cpu: boxes must be a contiguous (Nv, 4) int64 CPU tensor");
  const Grid grid{width, height, (width + kTile - 1) / kTile, (height + kTile - 1) / kTile};
  return bin_tiles_impl(boxes, grid);
}

// Normals from depth (surfels.depth_to_normal): P(y, x) = z(y, x) K^-1 (x + 0.5, y + 0.5, 1),
// c = (P(y+1, x) - P(y-1, x)) x (P(y, x+1) - P(y, x-1)), n = c / max(|c|, 1e-12), 1-px border 0.
// Computed in float64 and rounded to the depth's dtype.
struct DepthNormalGeom {
  int64_t H, W;
  double ki[9];
  void point(const double* z, int64_t y, int64_t x, double* out) const {
    const double px = static_cast<double>(x) + 0.5, py = static_cast<double>(y) + 0.5, d = z[y * W + x];
    for (int k = 0; k < 3; ++k) out[k] = d * (ki[3 * k] * px + ki[3 * k + 1] * py + ki[3 * k + 2]);
  }
  // the two difference vectors a = P(y+1,x) - P(y-1,x), b = P(y,x+1) - P(y,x-1) of an interior pixel
  void diffs(const double* z, int64_t y, int64_t x, double* a, double* b) const {
    double p0[3], p1[3];
    point(z, y + 1, x, p1);
    point(z, y - 1, x, p0);
    for (int k = 0; k < 3; ++k) a[k] = p1[k] - p0[k];
    point(z, y, x + 1, p1);
    point(z, y, x - 1, p0);
    for (int k = 0; k < 3; ++k) b[k] = p1[k] - p0[k];
  }
};

inline void cross3(const double* a, const double* b, double* c) {
  c[0] = a[1] * b[2] - a[2] * b[1];
  c[1] = a[2] * b[0] - a[0] * b[2];
  c[2] = a[0] * b[1] - a[1] * b[0];
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
  const double* z = z64.data_ptr<double>();
  const int64_t H = geo.H, W = geo.W;
  at::Tensor out = at::zeros({H, W, 3}, z64.options());
  double* n = out.data_ptr<double>();
#pragma omp parallel for schedule(static) num_threads(num_threads()) if (H * W >= kParallelPixels)
  for (int64_t y = 1; y < H - 1; ++y) {
    for (int64_t x = 1; x < W - 1; ++x) {
      double a[3], b[3], c[3];
      geo.diffs(z, y, x, a, b);
      cross3(a, b, c);
      const double len = std::max(std::sqrt(c[0] * c[0] + c[1] * c[1] + c[2] * c[2]), 1e-12);
      for (int k = 0; k < 3; ++k) n[3 * (y * W + x) + k] = c[k] / len;
    }
  }
  return out.to(depth_in.scalar_type());
}

// Gradient of depth_normal_forward: grad (H, W, 3) -> d depth (H, W).
at::Tensor depth_normal_backward(const at::Tensor& depth_in, const at::Tensor& kinv, const at::Tensor& grad_in) {
  const DepthNormalGeom geo = depth_normal_geom(depth_in, kinv);
  const int64_t H = geo.H, W = geo.W;
  TORCH_CHECK(grad_in.sizes() == at::IntArrayRef({H, W, 3}), "surfels_cpu: grad must be (H, W, 3)");
  const at::Tensor z64 = depth_in.to(at::kDouble).contiguous();
  const at::Tensor g64 = grad_in.to(at::kDouble).contiguous();
  const double* z = z64.data_ptr<double>();
  const double* g = g64.data_ptr<double>();
  // per interior pixel: gradients of its difference vectors a (vertical) and b (horizontal)
  std::vector<double> ga(static_cast<size_t>(H * W * 3), 0.0), gb(static_cast<size_t>(H * W * 3), 0.0);
  const int nt = num_threads();
#pragma omp parallel for schedule(static) num_threads(nt) if (H * W >= kParallelPixels)
  for (int64_t y = 1; y < H - 1; ++y) {
    for (int64_t x = 1; x < W - 1; ++x) {
      const int64_t p = y * W + x;
      double a[3], b[3], c[3];
      geo.diffs(z, y, x, a, b);
      cross3(a, b, c);
      const double norm = std::sqrt(c[0] * c[0] + c[1] * c[1] + c[2] * c[2]);
      const double* gn = g + 3 * p;
      double gc[3];
      if (norm > 1e-12) {  // n = c / |c|
        const double dot = (c[0] * gn[0] + c[1] * gn[1] + c[2] * gn[2]) / (norm * norm);
        for (int k = 0; k < 3; ++k) gc[k] = (gn[k] - c[k] * dot) / norm;
      } else {  // n = c / 1e-12
        for (int k = 0; k < 3; ++k) gc[k] = gn[k] / 1e-12;
      }
      cross3(b, gc, ga.data() + 3 * p);  // c = a x b: dL/da = b x gc, dL/db = gc x a
      cross3(gc, a, gb.data() + 3 * p);
    }
  }
  at::Tensor out = at::zeros({H, W}, z64.options());
  double* gz = out.data_ptr<double>();
  const double* A = ga.data();
  const double* B = gb.data();
#pragma omp parallel for schedule(static) num_threads(nt) if (H * W >= kParallelPixels)
  for (int64_t y = 0; y < H; ++y) {
    for (int64_t x = 0; x < W; ++x) {
      // P(y, x) enters a of (y-1, x) with +, a of (y+1, x) with -, b of (y, x-1) with +, b of (y, x+1) with -
      double gp[3] = {0.0, 0.0, 0.0};
      for (int k = 0; k < 3; ++k) {
        if (y >= 1) gp[k] += A[3 * ((y - 1) * W + x) + k];
        if (y + 1 < H) gp[k] -= A[3 * ((y + 1) * W + x) + k];
        if (x >= 1) gp[k] += B[3 * (y * W + x - 1) + k];
        if (x + 1 < W) gp[k] -= B[3 * (y * W + x + 1) + k];
      }
      const double px = static_cast<double>(x) + 0.5, py = static_cast<double>(y) + 0.5;
      double s = 0.0;
      for (int k = 0; k < 3; ++k) s += gp[k] * (geo.ki[3 * k] * px + geo.ki[3 * k + 1] * py + geo.ki[3 * k + 2]);
      gz[y * W + x] = s;
    }
  }
  return out.to(depth_in.scalar_type());
}

int64_t max_threads() { return num_threads(); }

}  // namespace

TORCH_LIBRARY(sage_surfels_cpu, m) {
  m.def("forward(Tensor table, Tensor payload, Tensor boxes, int width, int height, float near, float far) -> Tensor[]",
        &composite_forward);
  m.def(
      "backward(Tensor table, Tensor payload, Tensor boxes, Tensor offsets, Tensor lst, Tensor aux, Tensor auxi, "
      "Tensor g_pay, Tensor g_stats, int width, int height, float near, float far) -> Tensor[]",
      &composite_backward);
  m.def("bin_tiles(Tensor boxes, int width, int height) -> Tensor[]", &bin_tiles);
  m.def("depth_normal_forward(Tensor depth, Tensor kinv) -> Tensor", &depth_normal_forward);
  m.def("depth_normal_backward(Tensor depth, Tensor kinv, Tensor grad) -> Tensor", &depth_normal_backward);
  m.def("max_threads() -> int", &max_threads);
}
