// Native CPU batched eigensolver of symmetric 3x3 matrices: the fast path of shape.safe_eigh.
//
// eigh3(a) with a (N, 3, 3) float32 or float64, contiguous, returns eigenvalues (N, 3) ascending and
// eigenvectors (N, 3, 3) as columns (a = V diag(w) V^T), like torch.linalg.eigh(a) (UPLO="L": only the
// lower triangle a00, a10, a11, a20, a21, a22 is read).
//
// Method, per matrix, always in double precision (float32 inputs are widened, results rounded once):
//   * the matrix is scaled by the power of two that brings its largest |entry| into [0.5, 1) (exact
//     unless an entry underflows; squares can then neither overflow nor underflow; the eigenvalues
//     are scaled back at the end); a zero matrix gives zero eigenvalues and the identity;
//   * cyclic Jacobi: sweeps over the pairs (0,1), (0,2), (1,2), each rotation zeroing one off-diagonal
//     entry (the rotation of Numerical Recipes' form, with tau = s / (1 + c)), until every
//     off-diagonal entry is negligible: below 1e-18 (the scaled matrix's entries are up to ~1), or
//     too small to change either of its diagonal entries when added 100 times. A negligible entry is
//     set to zero without a rotation, a change far below the rounding of the input. The product of
//     the rotations is the eigenvector matrix, orthogonal to rounding whatever the eigenvalue gaps
//     are: repeated eigenvalues give an orthonormal basis of their eigenspace, with no special case.
//     At most kMaxSweeps sweeps (convergence is quadratic; 3x3 matrices need 3 or 4);
//   * the eigenvalues are sorted ascending (a stable 3-element sort: equal values keep their
//     Jacobi order), the columns follow;
//   * sign: each eigenvector is negated when its entry of largest magnitude (the first one among
//     equal magnitudes) is negative. LAPACK fixes no sign, so torch's eigenvectors may differ from
//     these by the sign of each column only (and, for repeated eigenvalues, by the choice of basis);
//   * a matrix with a non-finite lower-triangle entry gives NaN eigenvalues and eigenvectors.
//
// kLanes (8) matrices are solved together in structure-of-arrays form: every step is a loop over the
// lanes without branches, which the compiler vectorizes and which lets the processor overlap the
// lanes' chains of divisions and square roots. A lane that has converged (or a padding lane of the
// last block) takes the remaining sweeps of its block as rotations by t = 0, which leave every value
// bit for bit unchanged, so a matrix's result does not depend on its neighbours in the block.
//
// Threads: at::parallel_for over blocks (torch's intra-op threads, at::get_num_threads()), in chunks
// of kGrain matrices; the results do not depend on the thread count.
//
// eigh3_backward(w, V, gw, gV, gap) is the gap-clamped backward of shape.safe_eigh for one batch, per
// matrix (i, j over 0..2):
//   inner_ij = (V^T gV)_ij / safe_ij * [i != j] + [i == j] gw_i,  safe_ij = sign(w_j - w_i) max(|w_j - w_i|, gap)
//   (sign(0) = +1; gV absent: the first term is 0; gw absent: the second is),   G = V inner V^T,   ga = (G + G^T) / 2.
// It runs the same operations in the same order as the torch formula in shape.py (products of 3x3
// matrices summed over k = 0, 1, 2 in turn, as torch's batched matmul does for them; FMA contraction is
// off), so both give the same values bit for bit; over matrices in parallel (at::parallel_for).

#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <c10/util/Exception.h>
#include <c10/util/Optional.h>
#include <torch/library.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <tuple>

namespace {

constexpr int kMaxSweeps = 50;
// off-diagonal entries below this (the scaled matrix has entries up to ~1) are set to zero without a
// rotation: a perturbation far below the rounding of the input, as LAPACK's backward error is
constexpr double kNegligible = 1e-18;
constexpr int64_t kGrain = 1024;

constexpr int kLanes = 8;  // matrices per block (see the header)

struct Block {
  double m00[kLanes], m11[kLanes], m22[kLanes], m01[kLanes], m02[kLanes], m12[kLanes];
  double v[9][kLanes];  // v[3 * k + j]: row k, column j of the eigenvector matrix
  int exponent[kLanes];
  bool finite[kLanes];
};

// Whether the off-diagonal entry a between diagonal entries x and y is set to zero without a rotation.
inline bool negligible(double a, double x, double y) {
  const double g = 100.0 * std::fabs(a), ax = std::fabs(x), ay = std::fabs(y);
  return (std::fabs(a) < kNegligible) | ((ax + g == ax) & (ay + g == ay));
}

// The Jacobi rotation in the plane (p, q) of every lane: app, aqq, apq the entries (p, p), (q, q),
// (p, q); arp, arq the entries (r, p), (r, q) of the third index r; vp*, vq* the columns p and q of
// the eigenvector matrix. A lane whose (p, q) entry is negligible (see the header) gets t = 0.
inline void rotate(double* __restrict__ app, double* __restrict__ aqq, double* __restrict__ apq,
                   double* __restrict__ arp, double* __restrict__ arq, double* __restrict__ vp0,
                   double* __restrict__ vp1, double* __restrict__ vp2, double* __restrict__ vq0,
                   double* __restrict__ vq1, double* __restrict__ vq2) {
  for (int l = 0; l < kLanes; ++l) {
    const double a = apq[l], x = app[l], y = aqq[l];
    const bool skip = negligible(a, x, y);
    // tangent of the rotation angle: the root of smaller magnitude of t^2 + 2 theta t - 1 = 0 with
    // theta = (y - x) / (2 a), written without the division by a:
    // t = sign(h) 2 a / (|h| + sqrt(h^2 + 4 a^2)), h = y - x (sign(0) = +1); neither overflow (the
    // rotations keep the Frobenius norm, < 3) nor underflow (|a| >= kNegligible unless skipped)
    const double h = y - x;
    const double den = std::fabs(h) + std::sqrt(h * h + 4.0 * a * a);
    const double t0 = (h < 0.0 ? -2.0 : 2.0) * a / (skip ? 1.0 : den);
    const double t = skip ? 0.0 : t0;
    const double c = 1.0 / std::sqrt(t * t + 1.0);
    const double s = t * c;
    const double tau = s / (1.0 + c);
    app[l] = x - t * a;
    aqq[l] = y + t * a;
    apq[l] = 0.0;
    const double rp = arp[l], rq = arq[l];
    arp[l] = rp - s * (rq + tau * rp);
    arq[l] = rq + s * (rp - tau * rq);
    const double p0 = vp0[l], q0 = vq0[l], p1 = vp1[l], q1 = vq1[l], p2 = vp2[l], q2 = vq2[l];
    vp0[l] = p0 - s * (q0 + tau * p0);
    vq0[l] = q0 + s * (p0 - tau * q0);
    vp1[l] = p1 - s * (q1 + tau * p1);
    vq1[l] = q1 + s * (p1 - tau * q1);
    vp2[l] = p2 - s * (q2 + tau * p2);
    vq2[l] = q2 + s * (p2 - tau * q2);
  }
}

// Load matrix a (9 values, row-major, lower triangle read) into lane l: finiteness, power-of-two
// scaling, identity eigenvectors. A non-finite or zero matrix enters as zeros (no rotation happens).
template <typename S>
inline void load_lane(const S* a, Block& b, int l) {
  double m[6] = {static_cast<double>(a[0]), static_cast<double>(a[4]), static_cast<double>(a[8]),
                 static_cast<double>(a[3]), static_cast<double>(a[6]), static_cast<double>(a[7])};
  double scale = 0.0;
  bool finite = true;
  for (double x : m) {
    if (!std::isfinite(x)) finite = false;
    scale = std::fabs(x) > scale ? std::fabs(x) : scale;
  }
  int exponent = 0;
  if (finite && scale > 0.0) {
    std::frexp(scale, &exponent);  // scale = f * 2^exponent, f in [0.5, 1)
    for (double& x : m) x = std::ldexp(x, -exponent);  // exact unless an entry underflows
  } else {
    for (double& x : m) x = 0.0;
  }
  b.m00[l] = m[0], b.m11[l] = m[1], b.m22[l] = m[2], b.m01[l] = m[3], b.m02[l] = m[4], b.m12[l] = m[5];
  for (int k = 0; k < 9; ++k) b.v[k][l] = (k % 4 == 0) ? 1.0 : 0.0;
  b.exponent[l] = exponent;
  b.finite[l] = finite;
}

// Write lane l: eigenvalues ascending (scaled back), eigenvectors with the sign rule, or NaN.
template <typename S>
inline void store_lane(const Block& b, int l, S* w, S* v) {
  if (!b.finite[l]) {
    const S nan = std::numeric_limits<S>::quiet_NaN();
    for (int k = 0; k < 3; ++k) w[k] = nan;
    for (int k = 0; k < 9; ++k) v[k] = nan;
    return;
  }
  const int e = b.exponent[l];
  const double d[3] = {std::ldexp(b.m00[l], e), std::ldexp(b.m11[l], e), std::ldexp(b.m22[l], e)};
  int order[3] = {0, 1, 2};
  // stable sort of three: insertion sort with strict comparisons
  for (int i = 1; i < 3; ++i) {
    const int key = order[i];
    int j = i - 1;
    while (j >= 0 && d[order[j]] > d[key]) {
      order[j + 1] = order[j];
      --j;
    }
    order[j + 1] = key;
  }
  for (int col = 0; col < 3; ++col) {
    const int src = order[col];
    int big = 0;
    for (int k = 1; k < 3; ++k) {
      if (std::fabs(b.v[3 * k + src][l]) > std::fabs(b.v[3 * big + src][l])) big = k;
    }
    const double sign = b.v[3 * big + src][l] < 0.0 ? -1.0 : 1.0;
    w[col] = static_cast<S>(d[src]);
    for (int k = 0; k < 3; ++k) v[3 * k + col] = static_cast<S>(sign * b.v[3 * k + src][l]);
  }
}

// Solve the count <= kLanes matrices at a (9 values each); eigenvalues to w (3 each), eigenvectors to v
// (9 each, row-major, as columns).
template <typename S>
void eigh3_block(const S* a, S* w, S* v, int count) {
  Block b;
  for (int l = 0; l < kLanes; ++l) {
    if (l < count) {
      load_lane(a + 9 * l, b, l);
    } else {
      const S zero[9] = {};
      load_lane(zero, b, l);
    }
  }
  for (int sweep = 0; sweep < kMaxSweeps; ++sweep) {
    // done when every off-diagonal entry of every lane is negligible: they are set to zero, as a
    // sweep would (none of them would rotate, and zeroing one leaves the others' tests unchanged)
    bool busy = false;
    for (int l = 0; l < kLanes; ++l) {
      busy |= !(negligible(b.m01[l], b.m00[l], b.m11[l]) & negligible(b.m02[l], b.m00[l], b.m22[l]) &
                negligible(b.m12[l], b.m11[l], b.m22[l]));
    }
    if (!busy) {
      for (int l = 0; l < kLanes; ++l) b.m01[l] = b.m02[l] = b.m12[l] = 0.0;
      break;
    }
    // (p, q) = (0, 1), r = 2
    rotate(b.m00, b.m11, b.m01, b.m02, b.m12, b.v[0], b.v[3], b.v[6], b.v[1], b.v[4], b.v[7]);
    // (p, q) = (0, 2), r = 1
    rotate(b.m00, b.m22, b.m02, b.m01, b.m12, b.v[0], b.v[3], b.v[6], b.v[2], b.v[5], b.v[8]);
    // (p, q) = (1, 2), r = 0
    rotate(b.m11, b.m22, b.m12, b.m01, b.m02, b.v[1], b.v[4], b.v[7], b.v[2], b.v[5], b.v[8]);
  }
  for (int l = 0; l < count; ++l) store_lane(b, l, w + 3 * l, v + 9 * l);
}

std::tuple<at::Tensor, at::Tensor> eigh3(const at::Tensor& a) {
  TORCH_CHECK(a.device().is_cpu(), "eigh3: expected a CPU tensor, got ", a.device());
  TORCH_CHECK(a.dim() == 3 && a.size(1) == 3 && a.size(2) == 3, "eigh3: expected (N, 3, 3), got ", a.sizes());
  TORCH_CHECK(a.scalar_type() == at::kFloat || a.scalar_type() == at::kDouble,
              "eigh3: expected float32 or float64, got ", a.scalar_type());
  const at::Tensor ac = a.contiguous();
  const int64_t n = ac.size(0);
  at::Tensor evals = at::empty({n, 3}, ac.options());
  at::Tensor evecs = at::empty({n, 3, 3}, ac.options());
  AT_DISPATCH_FLOATING_TYPES(ac.scalar_type(), "eigh3", [&] {
    const scalar_t* src = ac.data_ptr<scalar_t>();
    scalar_t* w = evals.data_ptr<scalar_t>();
    scalar_t* v = evecs.data_ptr<scalar_t>();
    const int64_t blocks = (n + kLanes - 1) / kLanes;
    at::parallel_for(0, blocks, kGrain / kLanes, [&](int64_t begin, int64_t end) {
      for (int64_t i = begin; i < end; ++i) {
        const int64_t first = i * kLanes;
        const int count = static_cast<int>(std::min<int64_t>(kLanes, n - first));
        eigh3_block<scalar_t>(src + 9 * first, w + 3 * first, v + 9 * first, count);
      }
    });
  });
  return std::make_tuple(evals, evecs);
}

// a0 b0 + a1 b1 + a2 b2 summed from 0 in this order: an entry of a product of 3x3 matrices as torch's
// batched matmul forms it
template <typename S>
inline S dot3(S a0, S b0, S a1, S b1, S a2, S b2) {
  S m = S(0);
  m = m + a0 * b0;
  m = m + a1 * b1;
  return m + a2 * b2;
}

// one row-major 3x3 matrix of eigh3_backward (see the header): w (3,), V (9,), gw (3,) or null, gV (9,) or null
template <typename S>
void eigh3_backward_one(const S* w, const S* V, const S* gw, const S* gV, S gap, S* ga) {
  S inner[9], P[9], G[9];
  for (int i = 0; i < 3; ++i) {
    for (int j = 0; j < 3; ++j) {
      S t = S(0);
      if (gV) {
        const S diff = w[j] - w[i];
        const S mag = std::abs(diff);
        const S safe = (diff >= S(0) ? S(1) : S(-1)) * (mag < gap ? gap : mag);  // NaN stays NaN, as clamp_min
        t = dot3(V[i], gV[j], V[3 + i], gV[3 + j], V[6 + i], gV[6 + j]) / safe * (i == j ? S(0) : S(1));
      }
      if (gw) t = t + (i == j ? gw[i] : S(0));
      inner[3 * i + j] = t;
    }
  }
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j)
      P[3 * i + j] = dot3(V[3 * i], inner[j], V[3 * i + 1], inner[3 + j], V[3 * i + 2], inner[6 + j]);
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j)
      G[3 * i + j] = dot3(P[3 * i], V[3 * j], P[3 * i + 1], V[3 * j + 1], P[3 * i + 2], V[3 * j + 2]);
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) ga[3 * i + j] = S(0.5) * (G[3 * i + j] + G[3 * j + i]);
}

void check_batch(const at::Tensor& t, const at::Tensor& like, at::IntArrayRef shape, const char* what) {
  TORCH_CHECK(t.device().is_cpu() && t.scalar_type() == like.scalar_type() && t.sizes() == shape && t.is_contiguous(),
              "eigh3_backward: ", what, " must be a contiguous CPU tensor of shape ", shape, " and dtype ",
              like.scalar_type());
}

at::Tensor eigh3_backward(const at::Tensor& evals, const at::Tensor& evecs, const c10::optional<at::Tensor>& g_evals,
                          const c10::optional<at::Tensor>& g_evecs, double gap) {
  TORCH_CHECK(evecs.device().is_cpu() && evecs.dim() == 3 && evecs.size(1) == 3 && evecs.size(2) == 3 &&
                  evecs.is_contiguous() && (evecs.scalar_type() == at::kFloat || evecs.scalar_type() == at::kDouble),
              "eigh3_backward: evecs must be a contiguous CPU float32/float64 (N, 3, 3) tensor");
  const int64_t n = evecs.size(0);
  check_batch(evals, evecs, {n, 3}, "evals");
  const bool has_w = g_evals.has_value() && g_evals->defined(), has_v = g_evecs.has_value() && g_evecs->defined();
  if (has_w) check_batch(*g_evals, evecs, {n, 3}, "g_evals");
  if (has_v) check_batch(*g_evecs, evecs, {n, 3, 3}, "g_evecs");
  at::Tensor ga = at::empty({n, 3, 3}, evecs.options());
  AT_DISPATCH_FLOATING_TYPES(evecs.scalar_type(), "eigh3_backward", [&] {
    const scalar_t* w = evals.data_ptr<scalar_t>();
    const scalar_t* v = evecs.data_ptr<scalar_t>();
    const scalar_t* gw = has_w ? g_evals->data_ptr<scalar_t>() : nullptr;
    const scalar_t* gv = has_v ? g_evecs->data_ptr<scalar_t>() : nullptr;
    scalar_t* out = ga.data_ptr<scalar_t>();
    const scalar_t g = static_cast<scalar_t>(gap);
    at::parallel_for(0, n, kGrain, [&](int64_t begin, int64_t end) {
      for (int64_t b = begin; b < end; ++b)
        eigh3_backward_one<scalar_t>(w + 3 * b, v + 9 * b, gw ? gw + 3 * b : nullptr, gv ? gv + 9 * b : nullptr, g,
                                     out + 9 * b);
    });
  });
  return ga;
}

}  // namespace

TORCH_LIBRARY(sage_eigh3_cpu, m) {
  m.def("eigh3(Tensor a) -> (Tensor, Tensor)", &eigh3);
  m.def("eigh3_backward(Tensor evals, Tensor evecs, Tensor? g_evals, Tensor? g_evecs, float gap) -> Tensor",
        &eigh3_backward);
}
