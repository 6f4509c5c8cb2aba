// Fused CPU SDF network: value, feature and spatial gradient of the one-hidden-layer SDFNetwork, and the
// exact first-order backward of all three (the second-order terms of the gradient included). The
// backend="cpp" path of SDFNetwork (sage_core/fields/sdf.py); _cpp_sdf.py wraps it as one autograd node.
//
// The network, per point x (N, 3), with the box (lo, ext = hi - lo, centre c), the half extent h and
// the hash-grid layout as in sage_core/fields/hashgrid.py:
//   u = (x - lo) / ext, inside_k = (0 <= u_k <= 1), x01 = clamp(u, 0, 1) (NaN stays NaN)
//   xn = (x - c) / h
//   e_l = m_l * sum_q w_q(t_l) T[r_q]            per level l (F features), t_l = frac(x01 * s_l + 0.5)
//   in = [xn, e] (D = 3 + L*F),  z = W0 in + b0 (H),  a = softplus_beta(z),  out = W1 a + b1 (O = 1 + F_z)
//   sdf = h * out_0,  feature = out_1..   (without with_feature the forward computes out_0 alone)
// and its gradient, with sigma = softplus' (the logistic of beta z, 1 where beta z > threshold):
//   gz = (h W1_0) * sigma (H),  g_in = W0^T gz (D),  g_e = g_in[3:]
//   grad_k = g_in_k / h + (inside_k ? sum_j J_jk g_e_j : 0) / ext_k,   J = d e / d x01 (D-3, 3).
// Softplus follows torch: beta z > threshold gives z (first derivative 1), otherwise log1p(exp(beta z)) / beta;
// its second derivative is beta sigma (1 - sigma) where beta z < threshold and 0 elsewhere.
//
// Backward: given upstream gradients of sdf (N,), grad (N, 3), feature (N, F_z) and the encoding (N, L*F)
// (any of them may be absent), the adjoints run the formulas above in reverse:
//   ybar_k = inside_k ? Gg_k / ext_k : 0,   gbar_in = [Gg / h, J ybar]
//   gzbar = W0 gbar_in,   dW0 += gz gbar_in^T,   dW1_0 += h gzbar sigma,   zbar = (h W1_0) gzbar softplus''
//   obar = [h Gs, Gf],    dW1 += obar a^T, db1 += obar,   zbar += (W1^T obar) sigma
//   dW0 += zbar in^T, db0 += zbar,  inbar = W0^T zbar,  ebar = inbar[3:] + Genc
//   xbar_k = inbar_k / h + (inside_k ? sum_j J_jk ebar_j + sum_{i != k} ybar_i (K g_e)_ik : 0) / ext_k
//   dT[r_q] += m_l (w_q ebar_l + u_q g_e_l),  u_q = s_l sum_k (d w_q / d t_k) ybar_k
// where K = d^2 e / d x01^2 (its diagonal is 0: the interpolation is linear along each axis).
//
// Passes. Points go in blocks of kLanes (16 float / 8 double: 64 bytes), every per-point quantity
// stored as [row][lane]:
//   1. points (over blocks): x01, the inside flags and xn;
//   2. hash features (over levels, each level through all blocks, so that its table rows stay in this
//      core's caches; the next block's rows are prefetched): e, and J and K when needed, into a
//      per-block feature buffer;
//   3. the MLP (over blocks): forward values and gradient, or the backward's adjoints, x gradient and
//      the weight gradients;
//   4. backward only, the table gradient (over levels, points in order).
// The forward can keep its feature buffer (e, J and, when x may receive the gradient's gradient, K) for
// the backward, which then skips pass 2. Index and interpolation arithmetic, the matrix-vector products
// and the elementwise steps run over the lanes as GCC vectors; only table reads and gradient scatters
// are per lane. The kernel section at the end of this file is compiled twice, portable and for AVX2
// (#pragma GCC target), and the AVX2 build runs where the CPU has it; the operations are the same
// elementwise ones, so both give identical results. FMA contraction is off (build flags). float32 uses
// the polynomial exp/log of this file (within 2 ulp), float64 the C library.
//
// Threads (OpenMP, at most at::get_num_threads()): passes 1 and 3 over blocks, 2 and 4 over levels. The
// weight gradients are summed per fixed chunk of kChunkPoints points (points in order) and the chunk
// sums added in chunk order; each level's table-gradient rows are scattered by one thread, points in
// order. Results are therefore identical for any thread count.

#ifndef SAGE_SDF_KERNELS
#define SAGE_SDF_KERNELS 1

#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/empty_like.h>
#include <ATen/ops/zeros.h>
#include <ATen/ops/zeros_like.h>
#include <c10/util/Exception.h>
#include <c10/util/Optional.h>
#include <torch/library.h>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <type_traits>
#include <utility>
#include <vector>

#ifdef _OPENMP
#include <omp.h>
#endif

#if defined(__GNUC__) && !defined(__clang__)
#pragma GCC diagnostic ignored "-Wpsabi"  // 256/512-bit vector arguments of inline helpers
#endif

namespace {

template <typename S>
constexpr int kLanes = static_cast<int>(64 / sizeof(S));

constexpr int64_t kChunkPoints = 512;     // points per weight-gradient partial sum (fixed: thread-count independent)
constexpr int64_t kParallelPoints = 768;  // fewer points run on the calling thread
constexpr int64_t kParallelWork = 4096;   // (point, level) pairs below which a level pass runs on one thread

int num_threads() { return std::max(1, at::get_num_threads()); }

// ------------------------------------------------------------------------------------------------
// hash grid (the rules of hashgrid.py): a level's vertices per axis, table rows, first row, dense or hashed

struct Level {
  int64_t res, size, offset;
  bool dense;
};

// ------------------------------------------------------------------------------------------------
// the network and its scratch

template <typename S>
struct Net {
  int64_t N = 0, H = 0, O = 0, L = 0, F = 0, P = 0, D = 0;
  const S* W0 = nullptr;  // (H, D)
  const S* b0 = nullptr;  // (H,)
  const S* W1 = nullptr;  // (O, H)
  const S* b1 = nullptr;  // (O,)
  const S* T = nullptr;   // (rows, F)
  std::vector<S> W0T, W1T, v;  // (D, H), (H, O), h * W1[0, :]
  std::vector<Level> lv;
  std::vector<S> scale, maskS;
  std::vector<double> mask;
  S lo[3], ext[3], ctr[3];
  S h, beta, thr;
};

// Per-thread scratch of the MLP part of one block: every array is [rows][lanes].
template <typename S>
struct Work {
  std::vector<S> buf;
  S *z, *a, *sg, *s2, *out, *gz, *gin;  // forward
  S *gg, *genc, *yb, *ginb, *gzb, *zb, *ob, *ab, *inb, *ie;  // backward
  S *gzT, *zbT, *aT, *rT;  // [lanes][H] transposes for the weight gradients
  // weight-gradient sums of the current chunk: dW0^T (D, H), db0 (H), dW1 (O, H), db1 (O), contiguous
  std::vector<S> acc;
  S *accW0T = nullptr, *accb0 = nullptr, *accW1 = nullptr, *accb1 = nullptr;

  Work(const Net<S>& n, bool backward, bool weights) {
    constexpr int B = kLanes<S>;
    const int64_t H = n.H, D = n.D, O = n.O, P = n.P;
    const int64_t fwd = 3 * H + H + O + H + D;
    const int64_t bwd = backward ? 3 + P + 3 + D + H + H + O + H + D + P + 4 * H : 0;
    buf.assign(static_cast<size_t>((fwd + bwd) * B), S(0));
    S* p = buf.data();
    auto take = [&](int64_t rows) {
      S* r = p;
      p += rows * B;
      return r;
    };
    z = take(H), a = take(H), sg = take(H), s2 = take(H), out = take(O), gz = take(H), gin = take(D);
    if (backward) {
      gg = take(3), genc = take(P), yb = take(3), ginb = take(D);
      gzb = take(H), zb = take(H), ob = take(O), ab = take(H), inb = take(D), ie = take(P);
      gzT = take(H), zbT = take(H), aT = take(H), rT = take(H);
    }
    if (weights) {
      acc.assign(static_cast<size_t>(D * H + H + O * H + O), S(0));
      accW0T = acc.data(), accb0 = accW0T + D * H, accW1 = accb0 + H, accb1 = accW1 + O * H;
    }
  }
};

// The arrays of one call (null when absent / not wanted). Per-block arrays are [block][rows][lanes].
template <typename S>
struct Io {
  int64_t nblocks = 0;
  const S* X = nullptr;  // (N, 3) points
  S* X01 = nullptr;      // [block][3][lanes] box coordinates in [0, 1]
  S* INS = nullptr;      // [block][3][lanes] 1 where the unclamped coordinate is in [0, 1], else 0
  // [block][stride][lanes]: xn (rows 0..2), e (3..3+P), J (offJ.., 3P rows) and K (offK.., 3P rows)
  S* buf = nullptr;
  int64_t stride = 0, offJ = 0, offK = 0;
  // forward outputs
  S *sdf = nullptr, *grad = nullptr, *feat = nullptr, *enc = nullptr;
  // backward upstream gradients
  const S *Gs = nullptr, *Gg = nullptr, *Gf = nullptr, *Genc = nullptr;
  // backward outputs: d/dx (N, 3), and what the table pass needs per point: ebar and g_e [block][P][lanes],
  // ybar [block][3][lanes]
  S *xbar = nullptr, *ebar = nullptr, *ge = nullptr, *ybar = nullptr;
  bool weights = false;
};

// Rows per block of the feature buffer with J and / or K, and the first rows of J and K.
inline void buffer_layout(int64_t P, bool has_J, bool has_K, int64_t& stride, int64_t& offJ, int64_t& offK) {
  offJ = 3 + P;
  offK = offJ + (has_J ? 3 * P : 0);
  stride = offK + (has_K ? 3 * P : 0);
}

// Scratch of the level pass: corner rows and coordinates of two blocks (the current one and the next,
// whose rows are prefetched), and the corner values.
template <typename S>
struct LevelScratch {
  std::vector<uint32_t> rows;  // [2][8][lanes]
  std::vector<S> t, g;         // [2][3][lanes], [F][8][lanes]
  explicit LevelScratch(int64_t F)
      : rows(2 * 8 * kLanes<S>), t(2 * 3 * kLanes<S>), g(static_cast<size_t>(F * 8 * kLanes<S>)) {}
};

}  // namespace

// The kernels, compiled twice: portable, and for CPUs with AVX2 (chosen at run time by use_avx2()).
namespace {
namespace portable {
#include __FILE__
}  // namespace portable
}  // namespace

#if defined(__x86_64__) && defined(__GNUC__) && !defined(__clang__)
#define SAGE_SDF_AVX2 1
#pragma GCC push_options
#pragma GCC target("avx2")
namespace {
namespace avx2 {
#include __FILE__
}  // namespace avx2
}  // namespace
#pragma GCC pop_options
#endif

namespace {

// ------------------------------------------------------------------------------------------------
// run-time choice of the kernel build

template <typename S>
using BlockFn = void (*)(const Net<S>&, Work<S>&, const Io<S>&, int64_t);
template <typename S>
using LevelFn = void (*)(const Net<S>&, const Io<S>&, int64_t, LevelScratch<S>&);
template <typename S>
using ScatterFn = void (*)(const Net<S>&, const Io<S>&, int64_t, LevelScratch<S>&, S*);

std::atomic<bool> g_force_portable{false};  // tests compare the two builds

bool use_avx2() {
#ifdef SAGE_SDF_AVX2
  static const bool ok = __builtin_cpu_supports("avx2");
  return ok && !g_force_portable.load();
#else
  return false;
#endif
}

// The AVX2 build is instantiated for the training case only (float32, two features per level), which
// keeps the compile time down; float64 and other feature counts run the portable build.
template <typename S, int FC>
constexpr bool kHasAvx2Build = std::is_same_v<S, float> && FC == 2;

template <typename S, int FC>
BlockFn<S> pick_block(bool backward) {
#ifdef SAGE_SDF_AVX2
  if constexpr (kHasAvx2Build<S, FC>) {
    if (use_avx2()) return backward ? &avx2::backward_block<S, FC> : &avx2::forward_block<S, FC>;
  }
#endif
  return backward ? &portable::backward_block<S, FC> : &portable::forward_block<S, FC>;
}

template <typename S, int FC, bool kJ, bool kK>
LevelFn<S> pick_level() {
#ifdef SAGE_SDF_AVX2
  if constexpr (kHasAvx2Build<S, FC>) {
    if (use_avx2()) return &avx2::encode_level<S, FC, kJ, kK>;
  }
#endif
  return &portable::encode_level<S, FC, kJ, kK>;
}

template <typename S, int FC>
ScatterFn<S> pick_scatter(bool second) {
#ifdef SAGE_SDF_AVX2
  if constexpr (kHasAvx2Build<S, FC>) {
    if (use_avx2()) return second ? &avx2::scatter_level<S, FC, true> : &avx2::scatter_level<S, FC, false>;
  }
#endif
  return second ? &portable::scatter_level<S, FC, true> : &portable::scatter_level<S, FC, false>;
}

// Calls fn(std::integral_constant<int, FC>) with FC = 2 (the features per level of every preset, so the
// inner loops unroll) or FC = 0 (F read at run time).
template <typename Fn>
void dispatch_features(int64_t F, const Fn& fn) {
  if (F == 2)
    fn(std::integral_constant<int, 2>{});
  else
    fn(std::integral_constant<int, 0>{});
}

// ------------------------------------------------------------------------------------------------
// argument checks and the network description

std::vector<Level> read_levels(const at::Tensor& levels) {
  TORCH_CHECK(levels.device().is_cpu() && levels.scalar_type() == at::kLong && levels.dim() == 2 &&
                  levels.size(1) == 4 && levels.is_contiguous(),
              "sdf_cpu: levels must be a contiguous CPU int64 (L, 4) tensor");
  const int64_t* p = levels.data_ptr<int64_t>();
  std::vector<Level> out(levels.size(0));
  for (int64_t l = 0; l < levels.size(0); ++l) {
    const Level lv{p[4 * l], p[4 * l + 1], p[4 * l + 2], p[4 * l + 3] != 0};
    TORCH_CHECK(lv.res > 0 && lv.size > 0 && lv.offset >= 0, "sdf_cpu: bad level layout");
    // the index rules of cell_rows: a dense level holds its res^3 vertices (res <= 1024), a hashed level
    // has a power-of-two size
    TORCH_CHECK(lv.dense ? (lv.res <= 1024 && lv.res * lv.res * lv.res <= lv.size) : (lv.size & (lv.size - 1)) == 0,
                "sdf_cpu: level ", l, " has a layout the kernel does not handle (res ", lv.res, ", size ", lv.size,
                ", dense ", lv.dense, ")");
    out[l] = lv;
  }
  return out;
}

std::vector<double> read_doubles(const at::Tensor& v, int64_t L, const char* what) {
  TORCH_CHECK(v.device().is_cpu() && v.scalar_type() == at::kDouble && v.dim() == 1 && v.size(0) == L &&
                  v.is_contiguous(),
              "sdf_cpu: ", what, " must be a contiguous CPU float64 (L,) tensor");
  const double* p = v.data_ptr<double>();
  return std::vector<double>(p, p + L);
}

void check_param(const at::Tensor& t, const at::Tensor& x, std::vector<int64_t> shape, const char* what) {
  TORCH_CHECK(t.device().is_cpu() && t.scalar_type() == x.scalar_type() && t.is_contiguous() &&
                  t.sizes() == at::IntArrayRef(shape),
              "sdf_cpu: ", what, " must be a contiguous CPU tensor of shape ", at::IntArrayRef(shape), " and dtype ",
              x.scalar_type(), ", got ", t.sizes(), " ", t.scalar_type());
}

struct Args {
  const at::Tensor &x, &table, &w0, &b0, &w1, &b1, &levels, &scales, &mask, &box;
  double half_extent, beta, threshold;
};

template <typename S>
Net<S> make_net(const Args& a) {
  TORCH_CHECK(a.x.device().is_cpu() && a.x.dim() == 2 && a.x.size(1) == 3 && a.x.is_contiguous(),
              "sdf_cpu: x must be a contiguous CPU (N, 3) tensor");
  Net<S> n;
  n.lv = read_levels(a.levels);
  n.L = static_cast<int64_t>(n.lv.size());
  TORCH_CHECK(a.table.dim() == 2, "sdf_cpu: table must be (rows, F)");
  n.F = a.table.size(1);
  n.P = n.L * n.F;
  n.D = 3 + n.P;
  TORCH_CHECK(a.w0.dim() == 2 && a.w1.dim() == 2, "sdf_cpu: weights must be matrices");
  n.H = a.w0.size(0);
  n.O = a.w1.size(0);
  n.N = a.x.size(0);
  TORCH_CHECK(n.O >= 1 && n.H >= 1, "sdf_cpu: empty layer");
  check_param(a.table, a.x, {a.table.size(0), n.F}, "table");
  check_param(a.w0, a.x, {n.H, n.D}, "W0");
  check_param(a.b0, a.x, {n.H}, "b0");
  check_param(a.w1, a.x, {n.O, n.H}, "W1");
  check_param(a.b1, a.x, {n.O}, "b1");
  check_param(a.box, a.x, {3, 3}, "box");
  for (const Level& l : n.lv)
    TORCH_CHECK(l.offset + l.size <= a.table.size(0), "sdf_cpu: a level reaches past the table");
  TORCH_CHECK(a.table.size(0) <= int64_t(UINT32_MAX), "sdf_cpu: more than 2^32 table rows");
  const std::vector<double> sc = read_doubles(a.scales, n.L, "scales");
  n.mask = read_doubles(a.mask, n.L, "mask");
  for (int64_t l = 0; l < n.L; ++l) {
    n.scale.push_back(static_cast<S>(sc[l]));
    n.maskS.push_back(static_cast<S>(n.mask[l]));
  }
  n.W0 = a.w0.data_ptr<S>();
  n.b0 = a.b0.data_ptr<S>();
  n.W1 = a.w1.data_ptr<S>();
  n.b1 = a.b1.data_ptr<S>();
  n.T = a.table.data_ptr<S>();
  const S* bx = a.box.data_ptr<S>();
  for (int k = 0; k < 3; ++k) n.lo[k] = bx[k], n.ext[k] = bx[3 + k], n.ctr[k] = bx[6 + k];
  n.h = static_cast<S>(a.half_extent);
  n.beta = static_cast<S>(a.beta);
  n.thr = static_cast<S>(a.threshold);
  n.W0T.resize(n.D * n.H);
  for (int64_t j = 0; j < n.H; ++j)
    for (int64_t d = 0; d < n.D; ++d) n.W0T[d * n.H + j] = n.W0[j * n.D + d];
  n.W1T.resize(n.H * n.O);
  for (int64_t o = 0; o < n.O; ++o)
    for (int64_t j = 0; j < n.H; ++j) n.W1T[j * n.O + o] = n.W1[o * n.H + j];
  n.v.resize(n.H);
  for (int64_t j = 0; j < n.H; ++j) n.v[j] = n.h * n.W1[j];
  return n;
}

int point_threads(int64_t N) {
  const int nt = num_threads();
  return (nt > 1 && N >= kParallelPoints) ? nt : 1;
}

// ------------------------------------------------------------------------------------------------
// forward

// Passes 1 (the points, over blocks) and, when features, 2 (e and, as asked, J and K, over levels) into
// io's arrays; io.buf must have room for the layout in io. write_xn: also the xn rows of io.buf.
template <typename S, int FC>
void encode_points(const Net<S>& net, const Io<S>& io, bool write_xn, bool with_J, bool with_K, bool features) {
  const int64_t nb = io.nblocks;
  const int nt = point_threads(net.N);
#pragma omp parallel for schedule(static) num_threads(nt) if (nt > 1)
  for (int64_t b = 0; b < nb; ++b) portable::prepare_block<S>(net, io, b, write_xn);
  if (!features) return;
  const LevelFn<S> fn = with_K   ? pick_level<S, FC, true, true>()
                        : with_J ? pick_level<S, FC, true, false>()
                                 : pick_level<S, FC, false, false>();
  const int64_t L = net.L;
  const int lt = static_cast<int>(std::min<int64_t>(num_threads(), L));
  const int use = (lt > 1 && net.N * L >= kParallelWork) ? lt : 1;
#pragma omp parallel num_threads(use) if (use > 1)
  {
    LevelScratch<S> sc(net.F);
#pragma omp for schedule(dynamic, 1)
    for (int64_t l = 0; l < L; ++l) fn(net, io, l, sc);
  }
}

template <typename S, int FC>
void run_forward(const Net<S>& net, const Io<S>& io) {
  const int64_t nb = io.nblocks;
  const int nt = point_threads(net.N);
  encode_points<S, FC>(net, io, true, io.grad != nullptr, io.offK < io.stride, true);
  const BlockFn<S> fn = pick_block<S, FC>(false);
#pragma omp parallel num_threads(nt) if (nt > 1)
  {
    Work<S> w(net, false, false);
#pragma omp for schedule(dynamic, 4)
    for (int64_t b = 0; b < nb; ++b) fn(net, w, io, b);
  }
}

std::vector<at::Tensor> sdf_forward(const at::Tensor& x, const at::Tensor& table, const at::Tensor& w0,
                                    const at::Tensor& b0, const at::Tensor& w1, const at::Tensor& b1,
                                    const at::Tensor& levels, const at::Tensor& scales, const at::Tensor& mask,
                                    const at::Tensor& box, double half_extent, double beta, double threshold,
                                    bool with_grad, bool with_enc, bool keep, bool keep_second, bool with_feature) {
  TORCH_CHECK(x.scalar_type() == at::kFloat || x.scalar_type() == at::kDouble, "sdf_cpu: x must be float32 or float64");
  TORCH_CHECK(with_grad || !keep_second, "sdf_cpu: the second derivatives come with the gradient");
  const Args args{x, table, w0, b0, w1, b1, levels, scales, mask, box, half_extent, beta, threshold};
  const int64_t N = x.size(0);
  at::Tensor sdf = at::empty({N}, x.options());
  at::Tensor grad = with_grad ? at::empty({N, 3}, x.options()) : at::empty({0}, x.options());
  at::Tensor feat = with_feature ? at::empty({N, w1.size(0) - 1}, x.options()) : at::empty({0}, x.options());
  at::Tensor enc = with_enc ? at::empty({N, table.dim() == 2 ? levels.size(0) * table.size(1) : 0}, x.options())
                            : at::empty({0}, x.options());
  at::Tensor saved = at::empty({0}, x.options());
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "sdf_forward", [&] {
    using S = scalar_t;
    constexpr int B = kLanes<S>;
    const Net<S> net = make_net<S>(args);
    if (N == 0) return;
    Io<S> io;
    io.nblocks = (N + B - 1) / B;
    buffer_layout(net.P, with_grad, keep_second, io.stride, io.offJ, io.offK);
    at::Tensor feats = at::empty({io.nblocks * io.stride * B}, x.options());
    std::vector<S> x01(io.nblocks * 3 * B), ins(io.nblocks * 3 * B);
    io.X = x.data_ptr<S>();
    io.X01 = x01.data();
    io.INS = ins.data();
    io.buf = feats.data_ptr<S>();
    io.sdf = sdf.data_ptr<S>();
    io.grad = with_grad ? grad.data_ptr<S>() : nullptr;
    io.feat = with_feature ? feat.data_ptr<S>() : nullptr;
    io.enc = with_enc ? enc.data_ptr<S>() : nullptr;
    dispatch_features(net.F, [&](auto fc) { run_forward<S, decltype(fc)::value>(net, io); });
    if (keep) saved = feats;
  });
  return {sdf, grad, feat, enc, saved};
}

// ------------------------------------------------------------------------------------------------
// backward

// Zeroes the rows of a (rows, F) buffer that no active level owns (active levels zero their own rows).
template <typename S>
void zero_unowned_rows(S* buf, const Net<S>& n, int64_t rows) {
  std::vector<std::pair<int64_t, int64_t>> spans;
  for (int64_t l = 0; l < n.L; ++l)
    if (n.mask[l] != 0.0) spans.emplace_back(n.lv[l].offset, n.lv[l].offset + n.lv[l].size);
  std::sort(spans.begin(), spans.end());
  int64_t row = 0;
  for (const auto& sp : spans) {
    if (sp.first > row) std::fill(buf + row * n.F, buf + sp.first * n.F, S(0));
    row = std::max(row, sp.second);
  }
  if (rows > row) std::fill(buf + row * n.F, buf + rows * n.F, S(0));
}

// The table gradient: every active level on one thread (its rows zeroed there first, points in order),
// so the result is race-free and the same for any thread count.
template <typename S, int FC>
void table_pass(const Net<S>& net, const Io<S>& io, S* dT, bool second) {
  const ScatterFn<S> fn = pick_scatter<S, FC>(second);
  const int64_t L = net.L, F = net.F;
  const int lt = static_cast<int>(std::min<int64_t>(num_threads(), L));
  const int use = (lt > 1 && net.N * L >= kParallelWork) ? lt : 1;
#pragma omp parallel num_threads(use) if (use > 1)
  {
    LevelScratch<S> sc(F);
#pragma omp for schedule(dynamic, 1)
    for (int64_t l = 0; l < L; ++l) {
      if (net.mask[l] == 0.0) continue;
      const Level lev = net.lv[l];
      std::fill(dT + lev.offset * F, dT + (lev.offset + lev.size) * F, S(0));
      fn(net, io, l, sc, dT);
    }
  }
}

// The per-point pass over chunks of kChunkPoints points (weight-gradient partial sums into partial,
// per_chunk values per chunk), then the table pass into dT (when not null).
template <typename S, int FC>
void run_backward(const Net<S>& net, const Io<S>& io, bool encode, bool need_J, bool need_K, S* partial,
                  int64_t per_chunk, S* dT, int64_t rows, bool second) {
  constexpr int B = kLanes<S>;
  encode_points<S, FC>(net, io, encode, need_J, need_K, encode);
  const int64_t nblocks = io.nblocks, chunk_blocks = kChunkPoints / B;
  const int64_t nchunks = (nblocks + chunk_blocks - 1) / chunk_blocks;
  const bool weights = io.weights;
  const int nt = point_threads(net.N);
  const BlockFn<S> fn = pick_block<S, FC>(true);
#pragma omp parallel num_threads(nt) if (nt > 1)
  {
    Work<S> w(net, true, weights);
#pragma omp for schedule(dynamic, 1)
    for (int64_t c = 0; c < nchunks; ++c) {
      if (weights) std::fill(w.acc.begin(), w.acc.end(), S(0));
      const int64_t b_end = std::min(nblocks, (c + 1) * chunk_blocks);
      for (int64_t b = c * chunk_blocks; b < b_end; ++b) fn(net, w, io, b);
      if (weights) std::copy(w.acc.begin(), w.acc.end(), partial + c * per_chunk);
    }
  }
  if (dT) {
    zero_unowned_rows<S>(dT, net, rows);
    table_pass<S, FC>(net, io, dT, second);
  }
}

std::vector<at::Tensor> sdf_backward(const at::Tensor& x, const at::Tensor& table, const at::Tensor& w0,
                                     const at::Tensor& b0, const at::Tensor& w1, const at::Tensor& b1,
                                     const at::Tensor& levels, const at::Tensor& scales, const at::Tensor& mask,
                                     const at::Tensor& box, double half_extent, double beta, double threshold,
                                     const c10::optional<at::Tensor>& saved, bool saved_J, bool saved_K,
                                     const c10::optional<at::Tensor>& g_sdf, const c10::optional<at::Tensor>& g_grad,
                                     const c10::optional<at::Tensor>& g_feat, const c10::optional<at::Tensor>& g_enc,
                                     bool need_x, bool need_table, bool need_mlp) {
  TORCH_CHECK(x.scalar_type() == at::kFloat || x.scalar_type() == at::kDouble, "sdf_cpu: x must be float32 or float64");
  const Args args{x, table, w0, b0, w1, b1, levels, scales, mask, box, half_extent, beta, threshold};
  const int64_t N = x.size(0);
  const auto given = [](const c10::optional<at::Tensor>& t) { return t.has_value() && t->defined(); };
  const bool has_s = given(g_sdf), has_g = given(g_grad), has_f = given(g_feat), has_e = given(g_enc);
  const bool mlp_up = has_s || has_g || has_f;
  if (has_s) check_param(*g_sdf, x, {N}, "grad of sdf");
  if (has_g) check_param(*g_grad, x, {N, 3}, "grad of grad");
  if (has_f) check_param(*g_feat, x, {N, w1.size(0) - 1}, "grad of feature");
  if (has_e) check_param(*g_enc, x, {N, levels.size(0) * table.size(1)}, "grad of encoding");
  at::Tensor gx, gT, gW0, gb0, gW1, gb1;
  if (need_x) gx = at::zeros({N, 3}, x.options());
  if (need_table) gT = at::empty_like(table);
  const bool weights = need_mlp && mlp_up && N > 0;
  if (need_mlp) {
    gW0 = at::zeros_like(w0);
    gb0 = at::zeros_like(b0);
    gW1 = at::zeros_like(w1);
    gb1 = at::zeros_like(b1);
  }
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "sdf_backward", [&] {
    using S = scalar_t;
    constexpr int B = kLanes<S>;
    const Net<S> net = make_net<S>(args);
    const bool any_up = mlp_up || has_e;
    const bool table_work = need_table && any_up && N > 0;
    if (need_table && !table_work) gT.zero_();
    if (N == 0 || !any_up || !(need_x || table_work || weights)) return;
    const bool need_J = has_g || need_x, need_K = has_g && need_x;
    Io<S> io;
    io.nblocks = (N + B - 1) / B;
    // the forward's feature buffer when it holds what is needed, else a new one
    const bool reuse = given(saved) && (saved_J || !need_J) && (saved_K || !need_K);
    at::Tensor feats;
    if (reuse) {
      buffer_layout(net.P, saved_J, saved_K, io.stride, io.offJ, io.offK);
      TORCH_CHECK(saved->numel() == io.nblocks * io.stride * B && saved->scalar_type() == x.scalar_type() &&
                      saved->is_contiguous(),
                  "sdf_cpu: the saved feature buffer does not match");
      feats = *saved;
    } else {
      buffer_layout(net.P, need_J, need_K, io.stride, io.offJ, io.offK);
      feats = at::empty({io.nblocks * io.stride * B}, x.options());
    }
    std::vector<S> x01(io.nblocks * 3 * B), ins(io.nblocks * 3 * B);
    io.X = x.data_ptr<S>();
    io.X01 = x01.data();
    io.INS = ins.data();
    io.buf = feats.data_ptr<S>();
    io.Gs = has_s ? g_sdf->data_ptr<S>() : nullptr;
    io.Gg = has_g ? g_grad->data_ptr<S>() : nullptr;
    io.Gf = has_f ? g_feat->data_ptr<S>() : nullptr;
    io.Genc = has_e ? g_enc->data_ptr<S>() : nullptr;
    io.xbar = need_x ? gx.data_ptr<S>() : nullptr;
    io.weights = weights;
    std::vector<S> ebar, ge, ybar;
    if (table_work) {
      ebar.resize(io.nblocks * net.P * B);
      io.ebar = ebar.data();
      if (has_g) {
        ge.resize(io.nblocks * net.P * B);
        ybar.resize(io.nblocks * 3 * B);
        io.ge = ge.data();
        io.ybar = ybar.data();
      }
    }
    const int64_t H = net.H, D = net.D, O = net.O;
    const int64_t nW0 = H * D, nW1 = O * H, per_chunk = nW0 + H + nW1 + O;
    const int64_t nchunks = (N + kChunkPoints - 1) / kChunkPoints;
    std::vector<S> partial(weights ? static_cast<size_t>(nchunks * per_chunk) : 0);
    S* dT = table_work ? gT.data_ptr<S>() : nullptr;
    dispatch_features(net.F, [&](auto fc) {
      run_backward<S, decltype(fc)::value>(net, io, !reuse, need_J, need_K, partial.data(), per_chunk, dT,
                                           table.size(0), has_g);
    });
    if (weights) {  // chunk sums added in chunk order; dW0 comes transposed
      std::vector<S> total(per_chunk, S(0));
      for (int64_t c = 0; c < nchunks; ++c)
        for (int64_t i = 0; i < per_chunk; ++i) total[i] += partial[c * per_chunk + i];
      S* gw0 = gW0.data_ptr<S>();
      for (int64_t j = 0; j < H; ++j)
        for (int64_t d = 0; d < D; ++d) gw0[j * D + d] = total[d * H + j];
      std::copy(total.begin() + nW0, total.begin() + nW0 + H, gb0.data_ptr<S>());
      std::copy(total.begin() + nW0 + H, total.begin() + nW0 + H + nW1, gW1.data_ptr<S>());
      std::copy(total.begin() + nW0 + H + nW1, total.end(), gb1.data_ptr<S>());
    }
  });
  return {gx, gT, gW0, gb0, gW1, gb1};
}

bool has_avx2_path() { return use_avx2(); }

// Runs the portable build even where AVX2 is available (for tests); returns the previous setting.
bool force_portable(bool on) { return g_force_portable.exchange(on); }

}  // namespace

TORCH_LIBRARY(sage_sdf_cpu, m) {
  m.def(
      "forward(Tensor x, Tensor table, Tensor w0, Tensor b0, Tensor w1, Tensor b1, Tensor levels, Tensor scales, "
      "Tensor mask, Tensor box, float half_extent, float beta, float threshold, bool with_grad, bool with_enc, "
      "bool keep, bool keep_second, bool with_feature=True) -> Tensor[]",
      &sdf_forward);
  m.def(
      "backward(Tensor x, Tensor table, Tensor w0, Tensor b0, Tensor w1, Tensor b1, Tensor levels, Tensor scales, "
      "Tensor mask, Tensor box, float half_extent, float beta, float threshold, Tensor? saved, bool saved_J, "
      "bool saved_K, Tensor? g_sdf, Tensor? g_grad, Tensor? g_feature, Tensor? g_enc, bool need_x, bool need_table, "
      "bool need_mlp) -> Tensor[]",
      &sdf_backward);
  m.def("avx2() -> bool", &has_avx2_path);
  m.def("force_portable(bool on) -> bool", &force_portable);
}

#else  // SAGE_SDF_KERNELS: the kernel section, included once per build (see above)

// 256-bit vectors (GCC vector extensions; two 128-bit halves on CPUs without AVX). A block's row of
// kLanes values is two of them.
template <typename S>
struct SimdOf;
template <>
struct SimdOf<float> {
  typedef float type __attribute__((vector_size(32)));
};
template <>
struct SimdOf<double> {
  typedef double type __attribute__((vector_size(32)));
};
template <typename S>
using Vec = typename SimdOf<S>::type;
template <typename S>
constexpr int kVecLen = static_cast<int>(32 / sizeof(S));

template <typename S>
inline Vec<S> vload(const S* p) {
  Vec<S> v;
  std::memcpy(&v, p, sizeof v);
  return v;
}
template <typename S>
inline void vstore(S* p, const Vec<S>& v) {
  std::memcpy(p, &v, sizeof v);
}
template <typename S>
inline Vec<S> vbroadcast(S x) {
  return x - Vec<S>{};  // x - 0 is x for every x (unlike 0 + x for x = -0), so this folds to a broadcast
}

// One block row (kLanes values) as two native vectors, with elementwise arithmetic, comparisons
// (RowMask) and select.
template <typename S>
struct Row {
  Vec<S> a, b;  // lanes [0, VL) and [VL, 2 VL)
};
template <typename S>
using MaskVec = decltype(Vec<S>{} < Vec<S>{});
template <typename S>
struct RowMask {
  MaskVec<S> a, b;
};

template <typename S>
inline Row<S> ld(const S* p) {
  return {vload<S>(p), vload<S>(p + kVecLen<S>)};
}
template <typename S>
inline void st(S* p, const Row<S>& r) {
  vstore<S>(p, r.a);
  vstore<S>(p + kVecLen<S>, r.b);
}
template <typename S>
inline Row<S> splat(S x) {
  const Vec<S> v = vbroadcast<S>(x);
  return {v, v};
}
template <typename S>
inline Row<S> select(const RowMask<S>& m, const Row<S>& x, const Row<S>& y) {
  return {m.a ? x.a : y.a, m.b ? x.b : y.b};
}
template <typename S>
inline RowMask<S> operator&(const RowMask<S>& x, const RowMask<S>& y) {
  return {x.a & y.a, x.b & y.b};
}

#define SAGE_ROW_ARITH(op)                                                   \
  template <typename S>                                                      \
  inline Row<S> operator op(const Row<S>& x, const Row<S>& y) {              \
    return {x.a op y.a, x.b op y.b};                                         \
  }                                                                          \
  template <typename S>                                                      \
  inline Row<S> operator op(const Row<S>& x, S y) {                          \
    return {x.a op y, x.b op y};                                             \
  }                                                                          \
  template <typename S>                                                      \
  inline Row<S> operator op(S x, const Row<S>& y) {                          \
    return {x op y.a, x op y.b};                                             \
  }                                                                          \
  template <typename S>                                                      \
  inline Row<S>& operator op##=(Row<S>& x, const Row<S>& y) {                \
    x = x op y;                                                              \
    return x;                                                                \
  }
SAGE_ROW_ARITH(+)
SAGE_ROW_ARITH(-)
SAGE_ROW_ARITH(*)
SAGE_ROW_ARITH(/)
#undef SAGE_ROW_ARITH

#define SAGE_ROW_COMPARE(op)                                                 \
  template <typename S>                                                      \
  inline RowMask<S> operator op(const Row<S>& x, S y) {                      \
    return {x.a op y, x.b op y};                                             \
  }
SAGE_ROW_COMPARE(<)
SAGE_ROW_COMPARE(<=)
SAGE_ROW_COMPARE(>)
SAGE_ROW_COMPARE(>=)
SAGE_ROW_COMPARE(!=)
#undef SAGE_ROW_COMPARE

// In-place transpose of a square tile of vectors: r[i][j] <- r[j][i].
inline void transpose_square(Vec<float> (&r)[8]) {
  typedef int32_t M __attribute__((vector_size(32)));
  const M lo = {0, 8, 1, 9, 4, 12, 5, 13}, hi = {2, 10, 3, 11, 6, 14, 7, 15};
  const M pl = {0, 1, 8, 9, 4, 5, 12, 13}, ph = {2, 3, 10, 11, 6, 7, 14, 15};
  const M hl = {0, 1, 2, 3, 8, 9, 10, 11}, hh = {4, 5, 6, 7, 12, 13, 14, 15};
  Vec<float> t[8], u[8];
  for (int i = 0; i < 4; ++i) {
    t[2 * i] = __builtin_shuffle(r[2 * i], r[2 * i + 1], lo);
    t[2 * i + 1] = __builtin_shuffle(r[2 * i], r[2 * i + 1], hi);
  }
  for (int i = 0; i < 2; ++i) {
    u[4 * i + 0] = __builtin_shuffle(t[4 * i], t[4 * i + 2], pl);
    u[4 * i + 1] = __builtin_shuffle(t[4 * i], t[4 * i + 2], ph);
    u[4 * i + 2] = __builtin_shuffle(t[4 * i + 1], t[4 * i + 3], pl);
    u[4 * i + 3] = __builtin_shuffle(t[4 * i + 1], t[4 * i + 3], ph);
  }
  for (int j = 0; j < 4; ++j) {
    r[j] = __builtin_shuffle(u[j], u[4 + j], hl);
    r[4 + j] = __builtin_shuffle(u[j], u[4 + j], hh);
  }
}
inline void transpose_square(Vec<double> (&r)[4]) {
  typedef int64_t M __attribute__((vector_size(32)));
  const M lo = {0, 4, 2, 6}, hi = {1, 5, 3, 7}, pl = {0, 1, 4, 5}, ph = {2, 3, 6, 7};
  const Vec<double> t0 = __builtin_shuffle(r[0], r[1], lo), t1 = __builtin_shuffle(r[0], r[1], hi);
  const Vec<double> t2 = __builtin_shuffle(r[2], r[3], lo), t3 = __builtin_shuffle(r[2], r[3], hi);
  r[0] = __builtin_shuffle(t0, t2, pl);
  r[1] = __builtin_shuffle(t1, t3, pl);
  r[2] = __builtin_shuffle(t0, t2, ph);
  r[3] = __builtin_shuffle(t1, t3, ph);
}

// ------------------------------------------------------------------------------------------------
// elementary functions: float32 uses branch-free approximations (within 2 ulp) that vectorize over
// the lanes; float64 uses the C library. log1p(e) is log(1 + e) plus (e - ((1 + e) - 1)) / (1 + e), the
// first-order correction for the rounding of 1 + e.

inline float bits_to_float(int32_t i) {
  float f;
  std::memcpy(&f, &i, sizeof f);
  return f;
}

inline int32_t float_to_bits(float f) {
  int32_t i;
  std::memcpy(&i, &f, sizeof i);
  return i;
}

// exp(y) for y in [-87, 88] (clamped: below -87 gives exp(-87) ~ 1.6e-38, NaN stays NaN)
inline float exp_approx(float y) {
  const float yc = y > 88.0f ? 88.0f : (y < -87.0f ? -87.0f : y);
  const float shifter = 12582912.0f;  // 1.5 * 2^23: adding and subtracting it rounds to an integer
  const float n = (yc * 1.44269504088896341f + shifter) - shifter;
  const float r = (yc - n * 0.693359375f) - n * -2.12194440e-4f;
  float p = 1.9875691500e-4f;
  p = p * r + 1.3981999507e-3f;
  p = p * r + 8.3334519073e-3f;
  p = p * r + 4.1665795894e-2f;
  p = p * r + 1.6666665459e-1f;
  p = p * r + 5.0000001201e-1f;
  p = (p * (r * r) + r) + 1.0f;
  const int32_t ni = static_cast<int32_t>(n);
  return p * bits_to_float((ni + 127) << 23);
}

// log(v) for v >= 1 (finite)
inline float log_approx(float v) {
  const int32_t bits = float_to_bits(v);
  int32_t k = ((bits >> 23) & 0xff) - 127;
  float m = bits_to_float((bits & 0x007fffff) | 0x3f800000);  // [1, 2)
  const bool big = m > 1.41421356f;
  m = big ? 0.5f * m : m;
  k = big ? k + 1 : k;
  const float f = m - 1.0f;
  const float z = f * f;
  float p = 7.0376836292e-2f;
  p = p * f - 1.1514610310e-1f;
  p = p * f + 1.1676998740e-1f;
  p = p * f - 1.2420140846e-1f;
  p = p * f + 1.4249322787e-1f;
  p = p * f - 1.6668057665e-1f;
  p = p * f + 2.0000714765e-1f;
  p = p * f - 2.4999993993e-1f;
  p = p * f + 3.3333331174e-1f;
  const float kf = static_cast<float>(k);
  float y = p * f * z;
  y = y + kf * -2.12194440e-4f;
  y = y - 0.5f * z;
  return (f + y) + kf * 0.693359375f;
}

inline float exp_fn(float y) { return exp_approx(y); }
inline double exp_fn(double y) { return std::exp(y); }
inline float log_fn(float v) { return log_approx(v); }
inline double log_fn(double v) { return std::log(v); }

// Softplus of W values z: a = softplus(z), sg = softplus'(z), s2 = softplus''(z) when kSecond. W values
// at a time so that the vectorized polynomial chains of several vectors interleave.
template <typename S, int W, bool kSecond>
inline void activate_chunk(const S* z, S beta, S inv_beta, S thr, S* a, S* sg, S* s2) {
  S y[W], e[W];
  for (int i = 0; i < W; ++i) y[i] = z[i] * beta;
  for (int i = 0; i < W; ++i) e[i] = exp_fn(y[i]);
  for (int i = 0; i < W; ++i) {
    const S v = S(1) + e[i];
    const S r = S(1) / v;
    const S sig = e[i] * r;
    const S lp = log_fn(v) + (e[i] - (v - S(1))) * r;  // log1p(e): log(1 + e) corrected for its rounding
    a[i] = y[i] > thr ? z[i] : lp * inv_beta;
    const S g = y[i] > thr ? S(1) : sig;
    sg[i] = g;
    if (kSecond) s2[i] = y[i] < thr ? (beta * g) * (S(1) - g) : S(0);
  }
}

// activate_chunk over n values (n a multiple of the lanes B)
template <typename S, int B>
inline void activate(const S* z, int64_t n, S beta, S thr, S* a, S* sg, S* s2) {
  const S ib = S(1) / beta;
  int64_t i = 0;
  if (s2) {
    for (; i + 2 * B <= n; i += 2 * B) activate_chunk<S, 2 * B, true>(z + i, beta, ib, thr, a + i, sg + i, s2 + i);
    for (; i < n; i += B) activate_chunk<S, B, true>(z + i, beta, ib, thr, a + i, sg + i, s2 + i);
  } else {
    for (; i + 2 * B <= n; i += 2 * B) activate_chunk<S, 2 * B, false>(z + i, beta, ib, thr, a + i, sg + i, nullptr);
    for (; i < n; i += B) activate_chunk<S, B, false>(z + i, beta, ib, thr, a + i, sg + i, nullptr);
  }
}

// ------------------------------------------------------------------------------------------------
// block building blocks (B = lanes; arrays [rows][B])

// out[r0 + i] = bias[r0 + i] + sum_c W[r0 + i, c] v[c] for i < NR (NR rows at once: independent
// chains, the accumulators in vector registers)
template <typename S, int B, int NR>
inline void matvec_rows(const S* W, int64_t r0, int64_t C, const S* bias, const S* v, S* out) {
  static_assert(B == 2 * kVecLen<S>, "a block row is two vectors");
  constexpr int VL = kVecLen<S>;
  Vec<S> acc[NR][2];
#pragma GCC unroll 8
  for (int i = 0; i < NR; ++i) {
    const Vec<S> b = vbroadcast<S>(bias ? bias[r0 + i] : S(0));
    acc[i][0] = b;
    acc[i][1] = b;
  }
  const S* w = W + r0 * C;
  for (int64_t c = 0; c < C; ++c) {
    const Vec<S> v0 = vload<S>(v + c * B), v1 = vload<S>(v + c * B + VL);
#pragma GCC unroll 8
    for (int i = 0; i < NR; ++i) {
      const Vec<S> k = vbroadcast<S>(w[i * C + c]);
      acc[i][0] += k * v0;
      acc[i][1] += k * v1;
    }
  }
#pragma GCC unroll 8
  for (int i = 0; i < NR; ++i) {
    vstore<S>(out + (r0 + i) * B, acc[i][0]);
    vstore<S>(out + (r0 + i) * B + VL, acc[i][1]);
  }
}

// out[r] = bias[r] + sum_c W[r, c] v[c]  (W row-major (R, C); bias may be null; v, out [.][B])
template <typename S, int B>
inline void matvec(const S* W, int64_t R, int64_t C, const S* bias, const S* v, S* out) {
  int64_t r = 0;
  for (; r + 4 <= R; r += 4) matvec_rows<S, B, 4>(W, r, C, bias, v, out);
  if (r + 2 <= R) {
    matvec_rows<S, B, 2>(W, r, C, bias, v, out);
    r += 2;
  }
  if (r < R) matvec_rows<S, B, 1>(W, r, C, bias, v, out);
}

// dst [B][R] = src [R][B], by square tiles of vectors
template <typename S, int B>
inline void transpose_lanes(const S* src, int64_t R, S* dst) {
  constexpr int VL = kVecLen<S>;
  int64_t r0 = 0;
  for (; r0 + VL <= R; r0 += VL) {
    for (int h = 0; h < B / VL; ++h) {
      Vec<S> v[VL];
      for (int i = 0; i < VL; ++i) v[i] = vload<S>(src + (r0 + i) * B + h * VL);
      transpose_square(v);
      for (int j = 0; j < VL; ++j) vstore<S>(dst + (h * VL + j) * R + r0, v[j]);
    }
  }
  for (; r0 < R; ++r0)
    for (int p = 0; p < B; ++p) dst[p * R + r0] = src[r0 * B + p];
}

// ar[c0 + c] += sum over lanes p of ur[p] vT[p][c0 + c] (+ ur2[p] v2T[p][c0 + c]) for c < NV vectors,
// lanes in order, the accumulators in vector registers
template <typename S, int B, bool kTwo, int NV>
inline void outer_tile(S* ar, const S* ur, const S* vT, const S* ur2, const S* v2T, int64_t C, int64_t c0) {
  constexpr int VL = kVecLen<S>;
  Vec<S> t[NV];
#pragma GCC unroll 8
  for (int i = 0; i < NV; ++i) t[i] = vload<S>(ar + c0 + i * VL);
  for (int p = 0; p < B; ++p) {
    const Vec<S> k = vbroadcast<S>(ur[p]);
    const S* v = vT + p * C + c0;
#pragma GCC unroll 8
    for (int i = 0; i < NV; ++i) t[i] += k * vload<S>(v + i * VL);
    if (kTwo) {
      const Vec<S> k2 = vbroadcast<S>(ur2[p]);
      const S* v2 = v2T + p * C + c0;
#pragma GCC unroll 8
      for (int i = 0; i < NV; ++i) t[i] += k2 * vload<S>(v2 + i * VL);
    }
  }
#pragma GCC unroll 8
  for (int i = 0; i < NV; ++i) vstore<S>(ar + c0 + i * VL, t[i]);
}

// acc[r, c] += sum over lanes p of u[r][p] vT[p][c] (+ u2[r][p] v2T[p][c]), lanes in order.
// u, u2: [R][B]; vT, v2T: [B][C]; acc: (R, C). Vectorized over c with the accumulators in registers.
template <typename S, int B, bool kTwo>
inline void accumulate_outer(S* acc, const S* u, const S* vT, const S* u2, const S* v2T, int64_t R, int64_t C) {
  constexpr int VL = kVecLen<S>;
  for (int64_t r = 0; r < R; ++r) {
    const S* ur = u + r * B;
    const S* ur2 = kTwo ? u2 + r * B : nullptr;
    S* ar = acc + r * C;
    int64_t c0 = 0;
    for (; c0 + 8 * VL <= C; c0 += 8 * VL) outer_tile<S, B, kTwo, 8>(ar, ur, vT, ur2, v2T, C, c0);
    if (c0 + 4 * VL <= C) {
      outer_tile<S, B, kTwo, 4>(ar, ur, vT, ur2, v2T, C, c0);
      c0 += 4 * VL;
    }
    for (; c0 + VL <= C; c0 += VL) outer_tile<S, B, kTwo, 1>(ar, ur, vT, ur2, v2T, C, c0);
    for (; c0 < C; ++c0) {  // the last C mod VL columns
      S t = ar[c0];
      for (int p = 0; p < B; ++p) {
        t += ur[p] * vT[p * C + c0];
        if (kTwo) t += ur2[p] * v2T[p * C + c0];
      }
      ar[c0] = t;
    }
  }
}

// acc[c] += sum over lanes p of vT[p][c], lanes in order (vT [B][C])
template <typename S, int B>
inline void accumulate_rows(S* acc, const S* vT, int64_t C) {
  for (int p = 0; p < B; ++p) {
    const S* v = vT + p * C;
    for (int64_t c = 0; c < C; ++c) acc[c] += v[c];
  }
}

// Block b's points: box coordinates X01 and inside flags INS, and (when write_xn) xn into the first three
// rows of the feature buffer. Lanes past the last point hold the box centre.
template <typename S>
inline void prepare_block(const Net<S>& net, const Io<S>& io, int64_t b, bool write_xn) {
  constexpr int B = kLanes<S>;
  const int64_t n0 = b * B;
  const int cnt = static_cast<int>(std::min<int64_t>(B, net.N - n0));
  S xs[3][B];
  for (int p = 0; p < B; ++p)
    for (int k = 0; k < 3; ++k) xs[k][p] = p < cnt ? io.X[(n0 + p) * 3 + k] : net.ctr[k];
  const Row<S> zero = splat<S>(0), one = splat<S>(1);
  S* x01 = io.X01 + b * 3 * B;
  S* ins = io.INS + b * 3 * B;
  S* xn = io.buf + b * io.stride * B;
  for (int k = 0; k < 3; ++k) {
    const Row<S> x = ld<S>(xs[k]);
    const Row<S> u = (x - net.lo[k]) / net.ext[k];
    st<S>(ins + k * B, select((u >= S(0)) & (u <= S(1)), one, zero));
    st<S>(x01 + k * B, select(u < S(0), zero, select(u > S(1), one, u)));  // NaN stays NaN
    if (write_xn) st<S>(xn + k * B, (x - net.ctr[k]) / net.h);
  }
}

// Table rows of the 8 corners of every lane at one level, and the interpolation coordinates t
// (rows [8][B], t [3][B]), one native vector of lanes at a time. Index rules of hashgrid.py: a dense
// level's index is below twice its size (cells reach res), so "mod size" is one conditional
// subtraction; a hashed level's size is a power of two (the table size T).
template <typename S, int B>
inline void cell_rows(const S* x01, S scale, const Level& lv, uint32_t* rows, S* t) {
  constexpr int VL = kVecLen<S>;
  typedef uint32_t U __attribute__((vector_size(VL * 4)));
  typedef int32_t I __attribute__((vector_size(VL * 4)));
  const S res = static_cast<S>(lv.res);
  const uint32_t size = static_cast<uint32_t>(lv.size), r = static_cast<uint32_t>(lv.res);
  const uint32_t offset = static_cast<uint32_t>(lv.offset);
  for (int h = 0; h < B / VL; ++h) {
    U cell[3];
    for (int k = 0; k < 3; ++k) {
      const Vec<S> pos = vload<S>(x01 + k * B + h * VL) * scale + S(0.5);
      // NaN (or anything outside the level) reads cell 0; its NaN weights still give NaN features.
      // In range pos >= 0, so truncation is the floor.
      const Vec<S> inside = ((pos >= S(0)) & (pos < res)) ? pos : vbroadcast<S>(0);
      const I ci = __builtin_convertvector(inside, I);
      vstore<S>(t + k * B + h * VL, pos - __builtin_convertvector(ci, Vec<S>));
      cell[k] = reinterpret_cast<const U&>(ci);
    }
    for (int q = 0; q < 8; ++q) {
      const U cx = cell[0] + static_cast<uint32_t>(q & 1), cy = cell[1] + static_cast<uint32_t>((q >> 1) & 1);
      const U cz = cell[2] + static_cast<uint32_t>((q >> 2) & 1);
      U idx;
      if (lv.dense) {
        const U i = cx + r * (cy + r * cz);
        idx = (i >= size) ? i - size : i;
      } else {
        idx = (cx ^ (cy * 2654435761u) ^ (cz * 805459861u)) & (size - 1);
      }
      idx += offset;
      std::memcpy(rows + q * B + h * VL, &idx, sizeof idx);
    }
  }
}

// Features of level l for one block from its corner rows (rows [8][B]) and coordinates (t [3][B]), into
// the block's feature buffer blk: e (row 3 + l F + f), and when asked J (offJ + 3 (l F + f) + k) and K
// (offK + 3 (l F + f) + pair, pairs (0,1), (0,2), (1,2)), the derivatives with respect to x01.
// g: scratch [F][8][B].
template <typename S, int FC, bool kJ, bool kK>
inline void interpolate_level(const Net<S>& net, int64_t l, const uint32_t* rl, const S* t, S* g, S* blk,
                              int64_t offJ, int64_t offK) {
  constexpr int B = kLanes<S>;
  const int64_t F = FC > 0 ? FC : net.F;
  const S s = net.scale[l], m = net.maskS[l], ms = m * s, mss = ms * s;
  // the corner values, all features of a table row read together
  for (int q = 0; q < 8; ++q)
    for (int p = 0; p < B; ++p) {
      const S* row = net.T + static_cast<int64_t>(rl[q * B + p]) * F;
      for (int64_t f = 0; f < F; ++f) g[(f * 8 + q) * B + p] = row[f];
    }
  // 1-D weights and their pairwise products (xy[i]: x bit i & 1, y bit i >> 1; likewise yz, xz)
  const Row<S> tx = ld<S>(t), ty = ld<S>(t + B), tz = ld<S>(t + 2 * B);
  const Row<S> ux = S(1) - tx, uy = S(1) - ty, uz = S(1) - tz;
  const Row<S> xy[4] = {ux * uy, tx * uy, ux * ty, tx * ty};
  for (int64_t f = 0; f < F; ++f) {
    const int64_t j = l * F + f;
    Row<S> tv[8];
    for (int q = 0; q < 8; ++q) tv[q] = ld<S>(g + (f * 8 + q) * B);
    Row<S> acc = splat<S>(0);
    for (int q = 0; q < 8; ++q) acc = acc + (xy[q & 3] * ((q & 4) ? tz : uz)) * tv[q];  // (w_x w_y) w_z
    st<S>(blk + (3 + j) * B, acc * m);
    if (kJ) {
      // d e / d t_k: differences along axis k weighted by the other two axes
      const Row<S> yz[4] = {uy * uz, ty * uz, uy * tz, ty * tz};
      const Row<S> xz[4] = {ux * uz, tx * uz, ux * tz, tx * tz};
      const Row<S> dx =
          ((yz[0] * (tv[1] - tv[0]) + yz[1] * (tv[3] - tv[2])) + yz[2] * (tv[5] - tv[4])) + yz[3] * (tv[7] - tv[6]);
      const Row<S> dy =
          ((xz[0] * (tv[2] - tv[0]) + xz[1] * (tv[3] - tv[1])) + xz[2] * (tv[6] - tv[4])) + xz[3] * (tv[7] - tv[5]);
      const Row<S> dz =
          ((xy[0] * (tv[4] - tv[0]) + xy[1] * (tv[5] - tv[1])) + xy[2] * (tv[6] - tv[2])) + xy[3] * (tv[7] - tv[3]);
      S* jj = blk + (offJ + 3 * j) * B;
      st<S>(jj, dx * ms);
      st<S>(jj + B, dy * ms);
      st<S>(jj + 2 * B, dz * ms);
    }
    if (kK) {
      // d^2 e / (d t_i d t_k): the mixed difference of each (i, k) face, weighted by the third axis
      const Row<S> a01 = uz * ((tv[3] - tv[2]) - (tv[1] - tv[0])) + tz * ((tv[7] - tv[6]) - (tv[5] - tv[4]));
      const Row<S> a02 = uy * ((tv[5] - tv[4]) - (tv[1] - tv[0])) + ty * ((tv[7] - tv[6]) - (tv[3] - tv[2]));
      const Row<S> a12 = ux * ((tv[6] - tv[4]) - (tv[2] - tv[0])) + tx * ((tv[7] - tv[5]) - (tv[3] - tv[1]));
      S* kk = blk + (offK + 3 * j) * B;
      st<S>(kk, a01 * mss);
      st<S>(kk + B, a02 * mss);
      st<S>(kk + 2 * B, a12 * mss);
    }
  }
}

// Level l for every block, in block order (a level's table rows stay in this core's caches); masked
// levels write zeros.
template <typename S, int FC, bool kJ, bool kK>
void encode_level(const Net<S>& net, const Io<S>& io, int64_t l, LevelScratch<S>& sc) {
  constexpr int B = kLanes<S>;
  const int64_t F = FC > 0 ? FC : net.F, nb = io.nblocks;
  if (net.mask[l] == 0.0) {
    for (int64_t b = 0; b < nb; ++b) {
      S* blk = io.buf + b * io.stride * B;
      std::fill(blk + (3 + l * F) * B, blk + (3 + (l + 1) * F) * B, S(0));
      if (kJ) std::fill(blk + (io.offJ + 3 * l * F) * B, blk + (io.offJ + 3 * (l + 1) * F) * B, S(0));
      if (kK) std::fill(blk + (io.offK + 3 * l * F) * B, blk + (io.offK + 3 * (l + 1) * F) * B, S(0));
    }
    return;
  }
  const Level lev = net.lv[l];
  const S scale = net.scale[l];
  cell_rows<S, B>(io.X01, scale, lev, sc.rows.data(), sc.t.data());
  for (int64_t b = 0; b < nb; ++b) {
    const int cur = static_cast<int>(b & 1), nxt = cur ^ 1;
    uint32_t* rn = sc.rows.data() + nxt * 8 * B;
    if (b + 1 < nb) {  // the next block's corners, prefetched while this block is interpolated
      cell_rows<S, B>(io.X01 + (b + 1) * 3 * B, scale, lev, rn, sc.t.data() + nxt * 3 * B);
      for (int q = 0; q < 8; q += 2)  // the x-neighbour of a corner is (almost always) on the same line
        for (int p = 0; p < B; ++p) __builtin_prefetch(net.T + static_cast<int64_t>(rn[q * B + p]) * F);
    }
    interpolate_level<S, FC, kJ, kK>(net, l, sc.rows.data() + cur * 8 * B, sc.t.data() + cur * 3 * B, sc.g.data(),
                                     io.buf + b * io.stride * B, io.offJ, io.offK);
  }
}

// gz = (h W1_0) sigma and g_in = W0^T gz
template <typename S, int B>
inline void gradient_of_input(const Net<S>& net, Work<S>& w) {
  for (int64_t j = 0; j < net.H; ++j) st<S>(w.gz + j * B, net.v[j] * ld<S>(w.sg + j * B));
  matvec<S, B>(net.W0T.data(), net.D, net.H, nullptr, w.gz, w.gin);
}

// sum over j < P of A[(3 j + k)][:] * v[j][:] for k = 0, 1, 2 (A: J or K, [P][3][B]; v: [P][B])
template <typename S, int B>
inline void contract3(const S* A, const S* v, int64_t P, Row<S> (&out)[3]) {
  out[0] = out[1] = out[2] = splat<S>(0);
  for (int64_t j = 0; j < P; ++j) {
    const Row<S> vj = ld<S>(v + j * B);
    for (int k = 0; k < 3; ++k) out[k] += ld<S>(A + (j * 3 + k) * B) * vj;
  }
}

// dst[(n0 + p) * R + r] = src[r][p] for the block's cnt points (src [R][B], dst (N, R))
template <typename S, int B>
inline void store_points(const S* src, int64_t R, int64_t n0, int cnt, S* dst) {
  if (cnt == B) {
    transpose_lanes<S, B>(src, R, dst + n0 * R);
    return;
  }
  for (int p = 0; p < cnt; ++p)
    for (int64_t r = 0; r < R; ++r) dst[(n0 + p) * R + r] = src[r * B + p];
}

// ------------------------------------------------------------------------------------------------
// forward block

template <typename S, int FC>
void forward_block(const Net<S>& net, Work<S>& w, const Io<S>& io, int64_t b) {
  constexpr int B = kLanes<S>;
  const int64_t H = net.H, P = net.P, Fz = net.O - 1, n0 = b * B;
  const int cnt = static_cast<int>(std::min<int64_t>(B, net.N - n0));
  const S* inp = io.buf + b * io.stride * B;  // [xn, e]
  matvec<S, B>(net.W0, H, net.D, net.b0, inp, w.z);
  activate<S, B>(w.z, H * B, net.beta, net.thr, w.a, w.sg, nullptr);
  matvec<S, B>(net.W1, io.feat ? net.O : 1, H, net.b1, w.a, w.out);  // each row on its own: sdf alone is row 0
  for (int p = 0; p < cnt; ++p) io.sdf[n0 + p] = w.out[p] * net.h;
  if (io.feat) store_points<S, B>(w.out + B, Fz, n0, cnt, io.feat);
  if (io.enc) store_points<S, B>(inp + 3 * B, P, n0, cnt, io.enc);
  if (!io.grad) return;
  gradient_of_input<S, B>(net, w);
  Row<S> d[3];
  contract3<S, B>(inp + io.offJ * B, w.gin + 3 * B, P, d);
  const S* ins = io.INS + b * 3 * B;
  S out[3][B];
  for (int k = 0; k < 3; ++k) {
    const Row<S> in_k = select(ld<S>(ins + k * B) != S(0), d[k], splat<S>(0));
    st<S>(out[k], ld<S>(w.gin + k * B) / net.h + in_k / net.ext[k]);
  }
  for (int p = 0; p < cnt; ++p)
    for (int k = 0; k < 3; ++k) io.grad[(n0 + p) * 3 + k] = out[k][p];
}

// ------------------------------------------------------------------------------------------------
// backward block (the per-point part; the table gradient is scattered afterwards per level)

template <typename S>
inline void load_rows(const S* src, int64_t n0, int cnt, int64_t rows, S* dst) {
  constexpr int B = kLanes<S>;
  for (int p = 0; p < B; ++p)
    for (int64_t r = 0; r < rows; ++r) dst[r * B + p] = p < cnt ? src[(n0 + p) * rows + r] : S(0);
}

template <typename S, int FC>
void backward_block(const Net<S>& net, Work<S>& w, const Io<S>& io, int64_t b) {
  constexpr int B = kLanes<S>;
  const int64_t H = net.H, D = net.D, O = net.O, P = net.P, n0 = b * B;
  const int cnt = static_cast<int>(std::min<int64_t>(B, net.N - n0));
  const bool has_g = io.Gg != nullptr, has_s = io.Gs != nullptr, has_f = io.Gf != nullptr;
  const bool mlp = has_g || has_s || has_f;
  const bool need_x = io.xbar != nullptr, need_table = io.ebar != nullptr;
  const S* inp = io.buf + b * io.stride * B;  // [xn, e]
  const S* J = inp + io.offJ * B;
  const S* K = inp + io.offK * B;
  const S* ins = io.INS + b * 3 * B;

  if (mlp) {
    matvec<S, B>(net.W0, H, D, net.b0, inp, w.z);
    activate<S, B>(w.z, H * B, net.beta, net.thr, w.a, w.sg, has_g ? w.s2 : nullptr);
    std::fill(w.zb, w.zb + H * B, S(0));
    if (has_g) {
      gradient_of_input<S, B>(net, w);
      load_rows<S>(io.Gg, n0, cnt, 3, w.gg);
      for (int k = 0; k < 3; ++k) {
        const Row<S> g = ld<S>(w.gg + k * B);
        st<S>(w.yb + k * B, select(ld<S>(ins + k * B) != S(0), g / net.ext[k], splat<S>(0)));
        st<S>(w.ginb + k * B, g / net.h);
      }
      const Row<S> y0 = ld<S>(w.yb), y1 = ld<S>(w.yb + B), y2 = ld<S>(w.yb + 2 * B);
      for (int64_t j = 0; j < P; ++j) {
        const S* jj = J + j * 3 * B;
        st<S>(w.ginb + (3 + j) * B, (ld<S>(jj) * y0 + ld<S>(jj + B) * y1) + ld<S>(jj + 2 * B) * y2);
      }
      matvec<S, B>(net.W0, H, D, nullptr, w.ginb, w.gzb);
      for (int64_t j = 0; j < H; ++j)
        st<S>(w.zb + j * B, (net.v[j] * ld<S>(w.gzb + j * B)) * ld<S>(w.s2 + j * B));
      if (io.weights) {  // row 0 of W1: h * gzbar * sigma
        S* r = w.ab;  // free until the first-order part below
        for (int64_t j = 0; j < H; ++j) st<S>(r + j * B, (net.h * ld<S>(w.gzb + j * B)) * ld<S>(w.sg + j * B));
        transpose_lanes<S, B>(r, H, w.rT);
        accumulate_rows<S, B>(w.accW1, w.rT, H);
      }
    }
    if (has_s || has_f) {
      for (int p = 0; p < B; ++p) w.ob[p] = (has_s && p < cnt) ? io.Gs[n0 + p] * net.h : S(0);
      if (has_f)
        load_rows<S>(io.Gf, n0, cnt, O - 1, w.ob + B);
      else
        std::fill(w.ob + B, w.ob + O * B, S(0));
      matvec<S, B>(net.W1T.data(), H, O, nullptr, w.ob, w.ab);
      for (int64_t j = 0; j < H; ++j)
        st<S>(w.zb + j * B, ld<S>(w.zb + j * B) + ld<S>(w.ab + j * B) * ld<S>(w.sg + j * B));
      if (io.weights) {
        transpose_lanes<S, B>(w.a, H, w.aT);
        accumulate_outer<S, B, false>(w.accW1, w.ob, w.aT, nullptr, nullptr, O, H);
        for (int64_t o = 0; o < O; ++o)
          for (int p = 0; p < B; ++p) w.accb1[o] += w.ob[o * B + p];
      }
    }
    if (io.weights) {
      transpose_lanes<S, B>(w.zb, H, w.zbT);
      if (has_g) {
        transpose_lanes<S, B>(w.gz, H, w.gzT);
        accumulate_outer<S, B, true>(w.accW0T, w.ginb, w.gzT, inp, w.zbT, D, H);
      } else {
        accumulate_outer<S, B, false>(w.accW0T, inp, w.zbT, nullptr, nullptr, D, H);
      }
      accumulate_rows<S, B>(w.accb0, w.zbT, H);
    }
    if (need_x || need_table) matvec<S, B>(net.W0T.data(), D, H, nullptr, w.zb, w.inb);
  } else {
    std::fill(w.inb, w.inb + D * B, S(0));
  }
  if (!(need_x || need_table)) return;
  // ebar = inbar[3:] + Genc
  if (io.Genc) {
    load_rows<S>(io.Genc, n0, cnt, P, w.genc);
    for (int64_t j = 0; j < P; ++j) st<S>(w.ie + j * B, ld<S>(w.inb + (3 + j) * B) + ld<S>(w.genc + j * B));
  } else {
    std::copy(w.inb + 3 * B, w.inb + (3 + P) * B, w.ie);
  }
  if (need_x) {
    Row<S> d[3];
    contract3<S, B>(J, w.ie, P, d);
    if (has_g) {
      Row<S> kg[3];  // sum_j g_e_j K_j for the pairs (0,1), (0,2), (1,2)
      contract3<S, B>(K, w.gin + 3 * B, P, kg);
      const Row<S> y0 = ld<S>(w.yb), y1 = ld<S>(w.yb + B), y2 = ld<S>(w.yb + 2 * B);
      d[0] += y1 * kg[0] + y2 * kg[1];
      d[1] += y0 * kg[0] + y2 * kg[2];
      d[2] += y0 * kg[1] + y1 * kg[2];
    }
    S out[3][B];
    for (int k = 0; k < 3; ++k) {
      const Row<S> in_k = select(ld<S>(ins + k * B) != S(0), d[k], splat<S>(0));
      st<S>(out[k], ld<S>(w.inb + k * B) / net.h + in_k / net.ext[k]);
    }
    for (int p = 0; p < cnt; ++p)
      for (int k = 0; k < 3; ++k) io.xbar[(n0 + p) * 3 + k] = out[k][p];
  }
  if (need_table) {
    // block layout, lanes past the last point zero (they scatter nothing)
    S* eb = io.ebar + b * P * B;
    std::copy(w.ie, w.ie + P * B, eb);
    if (has_g) {
      std::copy(w.gin + 3 * B, w.gin + (3 + P) * B, io.ge + b * P * B);
      std::copy(w.yb, w.yb + 3 * B, io.ybar + b * 3 * B);
    }
  }
}

// Level l of the table gradient, block by block (points in order):
//   dT[r_q] += m (w_q ebar_l + u_q g_e_l),  u_q = s sum_k (d w_q / d t_k) ybar_k  (the second term when kSecond)
// The weights and the contributions are computed over the lanes, the scatter per lane. The caller zeroes
// the level's rows.
template <typename S, int FC, bool kSecond>
void scatter_level(const Net<S>& net, const Io<S>& io, int64_t l, LevelScratch<S>& sc, S* dT) {
  constexpr int B = kLanes<S>;
  const int64_t F = FC > 0 ? FC : net.F, P = net.P;
  const Level lev = net.lv[l];
  const S s = net.scale[l], m = net.maskS[l];
  uint32_t* rl = sc.rows.data();
  S* t = sc.t.data();
  S* c = sc.g.data();  // contributions [F][8][B]
  for (int64_t b = 0; b < io.nblocks; ++b) {
    const int cnt = static_cast<int>(std::min<int64_t>(B, net.N - b * B));
    cell_rows<S, B>(io.X01 + b * 3 * B, s, lev, rl, t);
    const Row<S> tx = ld<S>(t), ty = ld<S>(t + B), tz = ld<S>(t + 2 * B);
    const Row<S> ux = S(1) - tx, uy = S(1) - ty, uz = S(1) - tz;
    const Row<S> xy[4] = {ux * uy, tx * uy, ux * ty, tx * ty};
    Row<S> u[8];
    if (kSecond) {
      const Row<S> y0 = ld<S>(io.ybar + b * 3 * B) * s, y1 = ld<S>(io.ybar + b * 3 * B + B) * s;
      const Row<S> y2 = ld<S>(io.ybar + b * 3 * B + 2 * B) * s;
      const Row<S> yz[4] = {uy * uz, ty * uz, uy * tz, ty * tz};
      const Row<S> xz[4] = {ux * uz, tx * uz, ux * tz, tx * tz};
      for (int q = 0; q < 8; ++q) {
        const int b0 = q & 1, b1 = (q >> 1) & 1, b2 = (q >> 2) & 1;
        const Row<S> d0 = yz[b1 | (b2 << 1)], d1 = xz[b0 | (b2 << 1)], d2 = xy[q & 3];
        u[q] = ((b0 ? d0 : S(0) - d0) * y0 + (b1 ? d1 : S(0) - d1) * y1) + (b2 ? d2 : S(0) - d2) * y2;
      }
    }
    for (int64_t f = 0; f < F; ++f) {
      const int64_t j = l * F + f;
      const Row<S> eb = ld<S>(io.ebar + (b * P + j) * B) * m;
      const Row<S> gb = kSecond ? ld<S>(io.ge + (b * P + j) * B) * m : splat<S>(0);
      for (int q = 0; q < 8; ++q) {
        const Row<S> w = xy[q & 3] * ((q & 4) ? tz : uz);
        st<S>(c + (f * 8 + q) * B, kSecond ? w * eb + u[q] * gb : w * eb);
      }
    }
    for (int p = 0; p < cnt; ++p)
      for (int q = 0; q < 8; ++q) {
        S* row = dT + static_cast<int64_t>(rl[q * B + p]) * F;
        for (int64_t f = 0; f < F; ++f) row[f] += c[(f * 8 + q) * B + p];
      }
  }
}

#endif  // SAGE_SDF_KERNELS
