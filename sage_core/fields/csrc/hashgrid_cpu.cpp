// Native CPU multi-resolution hash encoding: the backend="cpp" path of HashGrid.level_features.
//
// Same rules as the pure-torch reference (sage_core/fields/hashgrid.py, see its header):
//   * input x01 (N, 3) in [0, 1] (normalized and clamped by the caller), table (T, F), per level l:
//     res_l, size_l, offset_l, dense_l (int64 (L, 4)), scale_l and mask_l (float64 (L,), rounded to
//     the input dtype as the reference does);
//   * pos = x01 * scale + 0.5, cell = floor(pos), t = pos - cell; corner c = cell + bits(c);
//     index = (dense ? cx + res*(cy + res*cz) : (cx*1 ^ cy*2654435761 ^ cz*805459861) mod 2^32)
//     mod size + offset;
//   * w_c = w_x * w_y * w_z with w_k = t_k or 1 - t_k (explicit product, as the reference), features
//     summed over corners 0..7 in order and multiplied by mask_l. Levels with mask 0 are skipped:
//     zero features and zero gradients.
// Three passes: forward (features), backward (d/dx01 and d/dtable of <G, features>) and the
// backward of the backward (the exact second-order terms for d/dG, d/dtable and d/dx01 of
// <ggx, grad_x01> + <ggT, grad_table>), all in the input dtype (float32 or float64). The build
// disables FMA contraction so the forward matches the reference's operation order.
//
// Threads: OpenMP over levels (dynamic schedule), at most at::get_num_threads(). Every table
// gradient entry belongs to exactly one level, so each level's scatter runs on one thread in point
// order: the table gradients are race-free and identical for any thread count (each level also
// zeroes its own gradient rows just before its scatter). Per-point gradients (d/dx01) are written
// per level into an (L, N, 3) buffer and summed over levels in level order.

#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/zeros.h>
#include <ATen/ops/empty_like.h>
#include <ATen/ops/permute.h>
#include <c10/util/Exception.h>
#include <c10/util/Optional.h>
#include <torch/library.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <type_traits>
#include <utility>
#include <vector>

#ifdef _OPENMP
#include <omp.h>
#endif

namespace {

// below this many (point, level) pairs a pass runs on one thread (waking threads costs more)
constexpr int64_t kParallelWork = 4096;
// points whose gradients and corners the backward reads before it scatters them (their index arithmetic
// then runs while earlier scatters wait for memory)
constexpr int kBackwardBlock = 32;

int num_threads() { return std::max(1, at::get_num_threads()); }

struct Level {
  int64_t res, size, offset;
  bool dense;
  bool pow2;  // size is a power of two: index mod size is a mask
};

// The 8 corners of one point at one level: table row offsets, weights and weight derivatives.
template <typename S>
struct Corners {
  int64_t row[8];  // index * F
  S w[8];          // w_x * w_y * w_z
  S dw[8][3];      // d w / d t_k
  S t[3], omt[3];  // t and 1 - t
};

template <typename S, bool kDerivs = true>
__attribute__((always_inline)) inline void corners(const S* x, S scale, const Level& lv, int64_t F, Corners<S>& c) {
  int64_t cell[3];
  for (int k = 0; k < 3; ++k) {
    const S pos = x[k] * scale + S(0.5);
    const S fl = std::floor(pos);
    c.t[k] = pos - fl;
    c.omt[k] = S(1) - c.t[k];
    // x01 in [0, 1] gives 0 <= fl < res; anything else (NaN) indexes cell 0 so no read leaves the
    // table, while its NaN weights still poison the result as in the reference
    cell[k] = (fl >= S(0) && fl < static_cast<S>(lv.res)) ? static_cast<int64_t>(fl) : 0;
  }
  // pairwise products of the 1-D weights, indexed by the two bits of the pair's axes
  const S* t = c.t;
  const S* u = c.omt;
  const S xy[4] = {u[0] * u[1], t[0] * u[1], u[0] * t[1], t[0] * t[1]};
#pragma GCC unroll 8
  for (int q = 0; q < 8; ++q) {
    const int b0 = q & 1, b1 = (q >> 1) & 1, b2 = (q >> 2) & 1;
    const int64_t cx = cell[0] + b0, cy = cell[1] + b1, cz = cell[2] + b2;
    int64_t idx;
    if (lv.dense) {
      idx = cx + lv.res * (cy + lv.res * cz);
    } else {
      const uint32_t h = static_cast<uint32_t>(cx) ^ (static_cast<uint32_t>(cy) * 2654435761u) ^
                         (static_cast<uint32_t>(cz) * 805459861u);
      idx = static_cast<int64_t>(h);
    }
    if (idx >= lv.size) idx = lv.pow2 ? (idx & (lv.size - 1)) : idx % lv.size;
    c.row[q] = (idx + lv.offset) * F;
    c.w[q] = xy[q & 3] * (b2 ? t[2] : u[2]);  // (w_x * w_y) * w_z, the reference's order
  }
  if (!kDerivs) return;
  const S yz[4] = {u[1] * u[2], t[1] * u[2], u[1] * t[2], t[1] * t[2]};
  const S xz[4] = {u[0] * u[2], t[0] * u[2], u[0] * t[2], t[0] * t[2]};
#pragma GCC unroll 8
  for (int q = 0; q < 8; ++q) {
    const int b0 = q & 1, b1 = (q >> 1) & 1, b2 = (q >> 2) & 1;
    const S dyz = yz[b1 | (b2 << 1)], dxz = xz[b0 | (b2 << 1)], dxy = xy[q & 3];
    c.dw[q][0] = b0 ? dyz : -dyz;
    c.dw[q][1] = b1 ? dxz : -dxz;
    c.dw[q][2] = b2 ? dxy : -dxy;
  }
}

// d^2 w / (d t_k d t_j) for k != j (the diagonal is 0): sign_k * sign_j * w of the third axis.
template <typename S>
inline S hess(const Corners<S>& c, int q, int k, int j) {
  const int o = 3 - k - j;
  const int bk = (q >> k) & 1, bj = (q >> j) & 1, bo = (q >> o) & 1;
  const S wo = bo ? c.t[o] : c.omt[o];
  return ((bk == bj) ? S(1) : S(-1)) * wo;
}

std::vector<Level> read_levels(const at::Tensor& levels) {
  TORCH_CHECK(levels.device().is_cpu() && levels.scalar_type() == at::kLong && levels.dim() == 2 &&
                  levels.size(1) == 4 && levels.is_contiguous(),
              "hashgrid_cpu: levels must be a contiguous CPU int64 (L, 4) tensor");
  const int64_t* p = levels.data_ptr<int64_t>();
  std::vector<Level> out(levels.size(0));
  for (int64_t l = 0; l < levels.size(0); ++l) {
    out[l] = Level{p[4 * l], p[4 * l + 1], p[4 * l + 2], p[4 * l + 3] != 0, (p[4 * l + 1] & (p[4 * l + 1] - 1)) == 0};
    TORCH_CHECK(out[l].res > 0 && out[l].size > 0 && out[l].offset >= 0, "hashgrid_cpu: bad level layout");
  }
  return out;
}

template <typename S>
std::vector<S> read_scalars(const at::Tensor& v, int64_t L, const char* what) {
  TORCH_CHECK(v.device().is_cpu() && v.scalar_type() == at::kDouble && v.dim() == 1 && v.size(0) == L &&
                  v.is_contiguous(),
              "hashgrid_cpu: ", what, " must be a contiguous CPU float64 (L,) tensor");
  const double* p = v.data_ptr<double>();
  std::vector<S> out(L);
  for (int64_t l = 0; l < L; ++l) out[l] = static_cast<S>(p[l]);
  return out;
}

void check_inputs(const at::Tensor& x01, const at::Tensor& table, const std::vector<Level>& lv) {
  TORCH_CHECK(x01.device().is_cpu() && table.device().is_cpu(), "hashgrid_cpu: needs CPU tensors");
  TORCH_CHECK(x01.scalar_type() == at::kFloat || x01.scalar_type() == at::kDouble,
              "hashgrid_cpu: x01 must be float32 or float64");
  TORCH_CHECK(table.scalar_type() == x01.scalar_type(), "hashgrid_cpu: x01 and table dtypes differ");
  TORCH_CHECK(x01.dim() == 2 && x01.size(1) == 3 && x01.is_contiguous(), "hashgrid_cpu: x01 must be contiguous (N, 3)");
  TORCH_CHECK(table.dim() == 2 && table.is_contiguous(), "hashgrid_cpu: table must be contiguous (T, F)");
  for (const Level& l : lv)
    TORCH_CHECK(l.offset + l.size <= table.size(0), "hashgrid_cpu: a level reaches past the table");
}

void check_like(const at::Tensor& t, const at::Tensor& ref, at::IntArrayRef shape, const char* what) {
  TORCH_CHECK(t.device().is_cpu() && t.scalar_type() == ref.scalar_type() && t.sizes() == shape && t.is_contiguous(),
              "hashgrid_cpu: ", what, " must be a contiguous CPU tensor of shape ", shape, " and dtype ",
              ref.scalar_type());
}

// Threads for a pass over L levels of N points (1: run on the calling thread).
int level_threads(int64_t L, int64_t N) {
  const int nt = static_cast<int>(std::min<int64_t>(num_threads(), L));
  return (nt > 1 && N * L >= kParallelWork) ? nt : 1;
}

// Runs body(level) for every unmasked level, in parallel over levels.
template <typename Body>
void for_levels(const std::vector<Level>& lv, const std::vector<double>& mask, int64_t N, const Body& body) {
  const int64_t L = static_cast<int64_t>(lv.size());
  const int nt = level_threads(L, N);
#pragma omp parallel for schedule(dynamic, 1) num_threads(nt) if (nt > 1)
  for (int64_t l = 0; l < L; ++l) {
    if (mask[l] != 0.0) body(l);
  }
}

std::vector<double> mask_values(const at::Tensor& mask, int64_t L) { return read_scalars<double>(mask, L, "mask"); }

// Zeroes the rows of a (rows, F) table-shaped buffer that no active level owns (masked levels and any
// rows past the last level). Active levels zero their own rows just before scattering into them, on
// the thread that owns the level, so those rows are written while in cache.
template <typename S>
void zero_unowned_rows(S* buf, const std::vector<Level>& lv, const std::vector<double>& mask, int64_t rows, int64_t F) {
  std::vector<std::pair<int64_t, int64_t>> spans;  // active [begin, end) row ranges
  for (size_t l = 0; l < lv.size(); ++l)
    if (mask[l] != 0.0) spans.emplace_back(lv[l].offset, lv[l].offset + lv[l].size);
  std::sort(spans.begin(), spans.end());
  int64_t row = 0;
  for (const auto& sp : spans) {
    if (sp.first > row) std::fill(buf + row * F, buf + sp.first * F, S(0));
    row = std::max(row, sp.second);
  }
  if (rows > row) std::fill(buf + row * F, buf + rows * F, S(0));
}

// Per-point feature scratch: on the stack for a compile-time F (FC > 0), else on the heap.
template <typename S, int FC>
struct Scratch {
  S fixed[FC > 0 ? FC : 1];
  std::vector<S> heap;
  explicit Scratch(int64_t F) : heap(FC > 0 ? 0 : F) {}
  S& operator[](int64_t i) {
    if constexpr (FC > 0) return fixed[i];
    return heap[i];
  }
};

// Calls fn(std::integral_constant<int, FC>) with FC = F for the common feature counts (so the inner
// loops unroll), FC = 0 (runtime F) otherwise.
template <typename Fn>
void dispatch_features(int64_t F, const Fn& fn) {
  switch (F) {
    case 1: fn(std::integral_constant<int, 1>{}); break;
    case 2: fn(std::integral_constant<int, 2>{}); break;
    case 4: fn(std::integral_constant<int, 4>{}); break;
    case 8: fn(std::integral_constant<int, 8>{}); break;
    default: fn(std::integral_constant<int, 0>{}); break;
  }
}

// ---------------------------------------------------------------------------------------------
// forward: feats (N, L, F)

template <typename S, int FC>
void forward_impl(const at::Tensor& x01, const at::Tensor& table, const std::vector<Level>& lv,
                  const std::vector<S>& scale, const std::vector<S>& maskS, const std::vector<double>& mask,
                  S* out, int64_t sn, int64_t sl) {
  const int64_t N = x01.size(0), F = FC > 0 ? FC : table.size(1);
  const S* x = x01.data_ptr<S>();
  const S* T = table.data_ptr<S>();
  for_levels(lv, mask, N, [&](int64_t l) {
    Corners<S> c;
    Scratch<S, FC> acc(F);
    const Level lev = lv[l];
    const S s = scale[l], ml = maskS[l];
    for (int64_t n = 0; n < N; ++n) {
      corners<S, false>(x + 3 * n, s, lev, F, c);
      for (int64_t f = 0; f < F; ++f) acc[f] = S(0);
#pragma GCC unroll 8
      for (int q = 0; q < 8; ++q) {
        const S* row = T + c.row[q];
        for (int64_t f = 0; f < F; ++f) acc[f] = acc[f] + c.w[q] * row[f];
      }
      S* o = out + n * sn + l * sl;
      for (int64_t f = 0; f < F; ++f) o[f] = acc[f] * ml;
    }
  });
}

at::Tensor encode_forward(const at::Tensor& x01, const at::Tensor& table, const at::Tensor& levels,
                          const at::Tensor& scales, const at::Tensor& mask) {
  const std::vector<Level> lv = read_levels(levels);
  check_inputs(x01, table, lv);
  const int64_t N = x01.size(0), F = table.size(1), L = static_cast<int64_t>(lv.size());
  const std::vector<double> m = mask_values(mask, L);
  // threads own levels; they write a level-major buffer (transposed afterwards) so that no two
  // threads write into the same cache line
  const bool level_major = level_threads(L, N) > 1;
  at::Tensor feats = level_major ? at::zeros({L, N, F}, x01.options()) : at::zeros({N, L, F}, x01.options());
  AT_DISPATCH_FLOATING_TYPES(x01.scalar_type(), "hashgrid_forward", [&] {
    const auto sc = read_scalars<scalar_t>(scales, L, "scales");
    const auto ms = read_scalars<scalar_t>(mask, L, "mask");
    const int64_t sn = level_major ? F : L * F, sl = level_major ? N * F : F;
    scalar_t* out = feats.data_ptr<scalar_t>();
    dispatch_features(F, [&](auto fc) {
      forward_impl<scalar_t, decltype(fc)::value>(x01, table, lv, sc, ms, m, out, sn, sl);
    });
  });
  return level_major ? feats.permute({1, 0, 2}).contiguous() : feats;
}

// ---------------------------------------------------------------------------------------------
// backward: gx (N, 3) = d<G, feats>/dx01 and gT (T, F) = d<G, feats>/dtable (undefined when not needed)

// One point's features (a compile-time count), kept in registers.
template <typename S, int FC>
struct FeatureValues {
  S v[FC > 0 ? FC : 1];
};

// gT[row_q] += w_q * g over one point's 8 corners (g (F,) held in registers for a compile-time F).
template <typename S, int FC>
__attribute__((always_inline)) inline void scatter_point(S* __restrict gT, const Corners<S>& c, const S* __restrict g,
                                                         int64_t F) {
  if constexpr (FC > 0) {
    FeatureValues<S, FC> gv;
#pragma GCC unroll 16
    for (int f = 0; f < FC; ++f) gv.v[f] = g[f];
#pragma GCC unroll 8
    for (int q = 0; q < 8; ++q) {
      S* row = gT + c.row[q];
      const S w = c.w[q];
#pragma GCC unroll 16
      for (int f = 0; f < FC; ++f) row[f] += w * gv.v[f];
    }
  } else {
    for (int q = 0; q < 8; ++q) {
      S* row = gT + c.row[q];
      for (int64_t f = 0; f < F; ++f) row[f] += c.w[q] * g[f];
    }
  }
}

// One level l of the backward over all points, in point order: the level's table-gradient rows (gT, when
// given) and each point's d/dx01 of the level (part, (N, 3), when given). Points go in blocks of
// kBackwardBlock: a block's gradients and corners first, then its scatters and gathers. The pointers are
// restrict (the table gradient is a buffer of its own), so the stores into it reload nothing.
template <typename S, int FC>
void backward_level(const Level lev, S s, S ml, int64_t l, int64_t N, int64_t L, int64_t F_table,
                    const S* __restrict x, const S* __restrict T, const S* __restrict g, S* __restrict gT,
                    S* __restrict part) {
  const int64_t F = FC > 0 ? FC : F_table;
  Corners<S> c[kBackwardBlock];
  bool any[kBackwardBlock];
  std::vector<S> gm_store(FC > 0 ? 0 : kBackwardBlock * F);
  S gm_fixed[FC > 0 ? kBackwardBlock * FC : 1];
  S* __restrict gm = FC > 0 ? gm_fixed : gm_store.data();
  if (gT) std::fill(gT + lev.offset * F, gT + (lev.offset + lev.size) * F, S(0));
  for (int64_t n0 = 0; n0 < N; n0 += kBackwardBlock) {
    const int nb = static_cast<int>(std::min<int64_t>(kBackwardBlock, N - n0));
    for (int i = 0; i < nb; ++i) {
      const S* gn = g + ((n0 + i) * L + l) * F;
      bool a = false;
      for (int64_t f = 0; f < F; ++f) {
        gm[i * F + f] = gn[f] * ml;
        a = a || gm[i * F + f] != S(0);
      }
      any[i] = a;
      if (!a) continue;  // the partial buffer starts at 0
      if (part) {
        corners(x + 3 * (n0 + i), s, lev, F, c[i]);
      } else {  // table gradient only: no weight derivatives needed
        corners<S, false>(x + 3 * (n0 + i), s, lev, F, c[i]);
      }
    }
    for (int i = 0; i < nb; ++i) {
      if (!any[i]) continue;
      const Corners<S>& ci = c[i];
      const S* gi = gm + i * F;
      if (gT) scatter_point<S, FC>(gT, ci, gi, F);
      if (!part) continue;
      S a0 = 0, a1 = 0, a2 = 0;
#pragma GCC unroll 8
      for (int q = 0; q < 8; ++q) {
        const S* row = T + ci.row[q];
        S gt = 0;
        for (int64_t f = 0; f < F; ++f) gt += gi[f] * row[f];
        a0 += ci.dw[q][0] * gt;
        a1 += ci.dw[q][1] * gt;
        a2 += ci.dw[q][2] * gt;
      }
      const int64_t n = n0 + i;
      part[3 * n + 0] = s * a0;
      part[3 * n + 1] = s * a1;
      part[3 * n + 2] = s * a2;
    }
  }
}

template <typename S, int FC>
void backward_impl(const at::Tensor& G, const at::Tensor& x01, const at::Tensor& table, const std::vector<Level>& lv,
                   const std::vector<S>& scale, const std::vector<S>& maskS, const std::vector<double>& mask,
                   S* gx_part, S* gT) {
  const int64_t N = x01.size(0), F = table.size(1), L = static_cast<int64_t>(lv.size());
  const S* x = x01.data_ptr<S>();
  const S* T = table.data_ptr<S>();
  const S* g = G.data_ptr<S>();
  if (!gx_part && !gT) return;
  for_levels(lv, mask, N, [&](int64_t l) {
    S* part = gx_part ? gx_part + l * N * 3 : nullptr;
    backward_level<S, FC>(lv[l], scale[l], maskS[l], l, N, L, F, x, T, g, gT, part);
  });
}

// out (N, 3) = sum over levels of part (L, N, 3), in level order
template <typename S>
void reduce_levels(const S* part, int64_t L, int64_t N, S* out) {
  const int nt = num_threads();
#pragma omp parallel for schedule(static) num_threads(nt) if (nt > 1 && N * L >= kParallelWork)
  for (int64_t i = 0; i < 3 * N; ++i) {
    S acc = 0;
    for (int64_t l = 0; l < L; ++l) acc += part[l * 3 * N + i];
    out[i] = acc;
  }
}

std::vector<at::Tensor> encode_backward(const at::Tensor& G, const at::Tensor& x01, const at::Tensor& table,
                                        const at::Tensor& levels, const at::Tensor& scales, const at::Tensor& mask,
                                        bool need_x, bool need_table) {
  const std::vector<Level> lv = read_levels(levels);
  check_inputs(x01, table, lv);
  const int64_t N = x01.size(0), F = table.size(1), L = static_cast<int64_t>(lv.size());
  check_like(G, x01, {N, L, F}, "grad_feats");
  const std::vector<double> m = mask_values(mask, L);
  at::Tensor gx, gT, part;
  if (need_x) {
    gx = at::empty({N, 3}, x01.options());
    part = at::zeros({L, N, 3}, x01.options());
  }
  if (need_table) gT = at::empty_like(table);
  AT_DISPATCH_FLOATING_TYPES(x01.scalar_type(), "hashgrid_backward", [&] {
    const auto sc = read_scalars<scalar_t>(scales, L, "scales");
    const auto ms = read_scalars<scalar_t>(mask, L, "mask");
    scalar_t* px = need_x ? part.data_ptr<scalar_t>() : nullptr;
    scalar_t* pt = need_table ? gT.data_ptr<scalar_t>() : nullptr;
    if (pt) zero_unowned_rows<scalar_t>(pt, lv, m, table.size(0), F);
    dispatch_features(F, [&](auto fc) {
      backward_impl<scalar_t, decltype(fc)::value>(G, x01, table, lv, sc, ms, m, px, pt);
    });
    if (need_x) reduce_levels<scalar_t>(part.data_ptr<scalar_t>(), L, N, gx.data_ptr<scalar_t>());
  });
  return {gx, gT};
}

// ---------------------------------------------------------------------------------------------
// double backward. With gx = d<G, feats>/dx01 and gT = d<G, feats>/dtable, the scalar
//   Q = <ggx, gx> + <ggT, gT>
// is differentiated w.r.t. G (dG, (N, L, F)), the table (dT, (T, F)) and x01 (dx, (N, 3)).
// Per point and level, with s = scale, m = mask, u_q = s * sum_k dw_q/dt_k ggx_k, gt_q = <G, T[q]>:
//   dG = m * (sum_q u_q T[q] + sum_q w_q ggT[q])
//   dT[q] += m * u_q * G
//   dx_j += m * s * (sum_q sum_{k != j} s ggx_k d2w_q/dt_k dt_j gt_q + sum_q dw_q/dt_j <G, ggT[q]>)

template <typename S, int FC>
void double_backward_impl(const at::Tensor& G, const at::Tensor& x01, const at::Tensor& table, const S* ggx,
                          const S* ggT, const std::vector<Level>& lv, const std::vector<S>& scale,
                          const std::vector<S>& maskS, const std::vector<double>& mask, S* dG, int64_t sn,
                          int64_t sl, S* dT, S* dx_part) {
  const int64_t N = x01.size(0), F = FC > 0 ? FC : table.size(1), L = static_cast<int64_t>(lv.size());
  const S* x = x01.data_ptr<S>();
  const S* T = table.data_ptr<S>();
  const S* g = G.data_ptr<S>();
  for_levels(lv, mask, N, [&](int64_t l) {
    Corners<S> c;
    Scratch<S, FC> gm(F), acc(F);
    const Level lev = lv[l];
    const S s = scale[l], ml = maskS[l];
    if (dT) std::fill(dT + lev.offset * F, dT + (lev.offset + lev.size) * F, S(0));
    S* part = dx_part ? dx_part + l * N * 3 : nullptr;
    for (int64_t n = 0; n < N; ++n) {
      const S* gn = g + (n * L + l) * F;
      S a[3] = {0, 0, 0};  // s * ggx
      bool any_x = false;
      if (ggx) {
        for (int k = 0; k < 3; ++k) {
          a[k] = s * ggx[3 * n + k];
          any_x = any_x || a[k] != S(0);
        }
      }
      if (!any_x && !ggT) continue;
      for (int64_t f = 0; f < F; ++f) gm[f] = gn[f] * ml;
      corners(x + 3 * n, s, lev, F, c);
      for (int64_t f = 0; f < F; ++f) acc[f] = S(0);
      S d[3] = {0, 0, 0};
#pragma GCC unroll 8
      for (int q = 0; q < 8; ++q) {
        // one pass per corner: its table row is read once for dG, dT and dx
        if (any_x) {
          const S* row = T + c.row[q];
          const S u = c.dw[q][0] * a[0] + c.dw[q][1] * a[1] + c.dw[q][2] * a[2];
          if (dG)
            for (int64_t f = 0; f < F; ++f) acc[f] += u * row[f];
          if (dT) {
            S* drow = dT + c.row[q];
            for (int64_t f = 0; f < F; ++f) drow[f] += u * gm[f];
          }
          if (part) {
            S gt = 0;
            for (int64_t f = 0; f < F; ++f) gt += gm[f] * row[f];
            d[0] += (hess(c, q, 1, 0) * a[1] + hess(c, q, 2, 0) * a[2]) * gt;
            d[1] += (hess(c, q, 0, 1) * a[0] + hess(c, q, 2, 1) * a[2]) * gt;
            d[2] += (hess(c, q, 0, 2) * a[0] + hess(c, q, 1, 2) * a[1]) * gt;
          }
        }
        if (ggT) {
          const S* grow = ggT + c.row[q];
          if (dG)
            for (int64_t f = 0; f < F; ++f) acc[f] += c.w[q] * grow[f];
          if (part) {
            S gg = 0;
            for (int64_t f = 0; f < F; ++f) gg += gm[f] * grow[f];
            d[0] += c.dw[q][0] * gg;
            d[1] += c.dw[q][1] * gg;
            d[2] += c.dw[q][2] * gg;
          }
        }
      }
      if (dG) {
        S* o = dG + n * sn + l * sl;
        for (int64_t f = 0; f < F; ++f) o[f] = acc[f] * ml;
      }
      if (part) {
        for (int k = 0; k < 3; ++k) part[3 * n + k] = s * d[k];
      }
    }
  });
}

std::vector<at::Tensor> encode_double_backward(const at::Tensor& G, const at::Tensor& x01, const at::Tensor& table,
                                               const c10::optional<at::Tensor>& ggx,
                                               const c10::optional<at::Tensor>& ggT, const at::Tensor& levels,
                                               const at::Tensor& scales, const at::Tensor& mask, bool need_G,
                                               bool need_table, bool need_x) {
  const std::vector<Level> lv = read_levels(levels);
  check_inputs(x01, table, lv);
  const int64_t N = x01.size(0), F = table.size(1), L = static_cast<int64_t>(lv.size());
  check_like(G, x01, {N, L, F}, "grad_feats");
  const bool has_x = ggx.has_value() && ggx->defined();
  const bool has_T = ggT.has_value() && ggT->defined();
  if (has_x) check_like(*ggx, x01, {N, 3}, "grad of grad_x");
  if (has_T) check_like(*ggT, table, table.sizes(), "grad of grad_table");
  const std::vector<double> m = mask_values(mask, L);
  at::Tensor dG, dT, dx, part;
  const bool level_major = level_threads(L, N) > 1;  // see encode_forward
  if (need_G) dG = level_major ? at::zeros({L, N, F}, x01.options()) : at::zeros({N, L, F}, x01.options());
  if (need_table) dT = at::empty_like(table);
  if (need_x) {
    dx = at::empty({N, 3}, x01.options());
    part = at::zeros({L, N, 3}, x01.options());
  }
  AT_DISPATCH_FLOATING_TYPES(x01.scalar_type(), "hashgrid_double_backward", [&] {
    const auto sc = read_scalars<scalar_t>(scales, L, "scales");
    const auto ms = read_scalars<scalar_t>(mask, L, "mask");
    const scalar_t* gx_in = has_x ? ggx->data_ptr<scalar_t>() : nullptr;
    const scalar_t* gt_in = has_T ? ggT->data_ptr<scalar_t>() : nullptr;
    scalar_t* pg = need_G ? dG.data_ptr<scalar_t>() : nullptr;
    scalar_t* pt = need_table ? dT.data_ptr<scalar_t>() : nullptr;
    scalar_t* px = need_x ? part.data_ptr<scalar_t>() : nullptr;
    if (pt) zero_unowned_rows<scalar_t>(pt, lv, m, table.size(0), F);
    dispatch_features(F, [&](auto fc) {
      double_backward_impl<scalar_t, decltype(fc)::value>(G, x01, table, gx_in, gt_in, lv, sc, ms, m, pg,
                                                          level_major ? F : L * F, level_major ? N * F : F, pt, px);
    });
    if (need_x) reduce_levels<scalar_t>(part.data_ptr<scalar_t>(), L, N, dx.data_ptr<scalar_t>());
  });
  if (need_G && level_major) dG = dG.permute({1, 0, 2}).contiguous();
  return {dG, dT, dx};
}

int64_t max_threads() { return num_threads(); }

}  // namespace

TORCH_LIBRARY(sage_hashgrid_cpu, m) {
  m.def("forward(Tensor x01, Tensor table, Tensor levels, Tensor scales, Tensor mask) -> Tensor", &encode_forward);
  m.def(
      "backward(Tensor grad_feats, Tensor x01, Tensor table, Tensor levels, Tensor scales, Tensor mask, "
      "bool need_x, bool need_table) -> Tensor[]",
      &encode_backward);
  m.def(
      "double_backward(Tensor grad_feats, Tensor x01, Tensor table, Tensor? ggx, Tensor? ggtable, Tensor levels, "
      "Tensor scales, Tensor mask, bool need_grad_feats, bool need_table, bool need_x) -> Tensor[]",
      &encode_double_backward);
  m.def("max_threads() -> int", &max_threads);
}
