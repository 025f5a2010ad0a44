// The compiled CPU backend of the 3DGS rasterizer: the maths of projection.py, tiling.py and
// compositing.py (see their docstrings), forward and hand-written backward, multithreaded with
// OpenMP and registered as torch operators (torch.ops.interactavatar_gs.*).
//
// Conventions are those of the torch backend: OpenCV camera and pixel centres on integers,
// per-Gaussian maths in float64 whatever the input dtype, per-pixel compositing in the input
// dtype (float32 or float64), alpha = min(0.99, o exp(-q / 2)) skipped below 1/255, and a pixel
// stops before the Gaussian that would take its transmittance below 1e-4.
//
// Determinism: every output element is written by exactly one thread in a fixed order. Tiles
// write their own pixels; the backward writes each (tile, Gaussian) pair's gradient into its
// own slot and sums a Gaussian's slots in tile order afterwards, so the result does not depend
// on the thread count or the schedule.
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <torch/library.h>
#include <omp.h>
#if defined(__AVX__)
#include <immintrin.h>
#endif

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
#include <tuple>
#include <type_traits>
#include <vector>

namespace {

constexpr double kLowPass = 0.3;
constexpr double kAlphaMin = 1.0 / 255.0;
constexpr double kAlphaMax = 0.99;
constexpr double kTMin = 1e-4;
constexpr double kFovMargin = 0.3;
constexpr double kQuatEps2 = 1e-24;
constexpr double kMaxRadius = 1073741824.0;  // 2^30
// Values per (tile, Gaussian) pair gradient slot: mean x, y, conic a, b, c, opacity, r, g, b, depth.
constexpr int kPairGrad = 10;

// ---------------------------------------------------------------------------------------------
// Projection (projection.py)

struct Camera {
  double fx, fy, cx, cy;
  double rot[3][3];
  double trans[3];
  double lim_x_neg, lim_x_pos, lim_y_neg, lim_y_pos;  // fov_limits
  int width, height;
  double near_plane, far_plane;
};

Camera make_camera(const at::Tensor& K, const at::Tensor& view, int64_t width, int64_t height,
                   double near_plane, double far_plane) {
  TORCH_CHECK(K.scalar_type() == at::kDouble && view.scalar_type() == at::kDouble,
              "K and world_to_cam must be float64");
  const at::Tensor k = K.contiguous(), v = view.contiguous();
  const double* kp = k.const_data_ptr<double>();
  const double* vp = v.const_data_ptr<double>();
  Camera cam{};
  cam.fx = kp[0];
  cam.fy = kp[4];
  cam.cx = kp[2];
  cam.cy = kp[5];
  for (int i = 0; i < 3; ++i) {
    for (int j = 0; j < 3; ++j) cam.rot[i][j] = vp[4 * i + j];
    cam.trans[i] = vp[4 * i + 3];
  }
  const double margin_x = kFovMargin * 0.5 * width / cam.fx;
  const double margin_y = kFovMargin * 0.5 * height / cam.fy;
  cam.lim_x_neg = (cam.cx + 0.5) / cam.fx + margin_x;
  cam.lim_x_pos = (width - 0.5 - cam.cx) / cam.fx + margin_x;
  cam.lim_y_neg = (cam.cy + 0.5) / cam.fy + margin_y;
  cam.lim_y_pos = (height - 0.5 - cam.cy) / cam.fy + margin_y;
  cam.width = static_cast<int>(width);
  cam.height = static_cast<int>(height);
  cam.near_plane = near_plane;
  cam.far_plane = far_plane;
  return cam;
}

// Everything the projection of one Gaussian computes; the backward recomputes it.
struct Projected {
  bool in_depth;
  double x, y, z;  // camera point (the safe point (0, 0, 1) where culled by depth)
  double tx, ty;   // clamped x / z, y / z
  bool tx_free, ty_free;  // not clamped (the clamp passes the gradient)
  double jw[2][3];        // EWA Jacobian times the camera rotation
  double qn[4];           // normalised quaternion (w, x, y, z)
  double inv_norm;
  bool norm_free;  // the norm is above the clamp
  double rq[3][3];  // rotation of the Gaussian
  double bmat[2][3];  // jw rq
  double amat[2][3];  // bmat diag(scale)
  double a, b, c;  // 2D covariance with the low-pass
  bool finite;
  double u, v;  // projected mean
};

template <typename scalar_t>
Projected project_one(const Camera& cam, const scalar_t* mean, const scalar_t* quat, const scalar_t* scale) {
  Projected p{};
  double pc[3];
  for (int j = 0; j < 3; ++j) {
    pc[j] = static_cast<double>(mean[0]) * cam.rot[j][0] + static_cast<double>(mean[1]) * cam.rot[j][1] +
            static_cast<double>(mean[2]) * cam.rot[j][2] + cam.trans[j];
  }
  p.in_depth = pc[2] >= cam.near_plane && pc[2] <= cam.far_plane && std::isfinite(pc[0]) &&
               std::isfinite(pc[1]) && std::isfinite(pc[2]);
  if (!p.in_depth) {
    pc[0] = 0.0;
    pc[1] = 0.0;
    pc[2] = 1.0;
  }
  p.x = pc[0];
  p.y = pc[1];
  p.z = pc[2];
  p.u = cam.fx * p.x / p.z + cam.cx;
  p.v = cam.fy * p.y / p.z + cam.cy;

  const double rx = p.x / p.z, ry = p.y / p.z;
  p.tx = std::min(std::max(rx, -cam.lim_x_neg), cam.lim_x_pos);
  p.ty = std::min(std::max(ry, -cam.lim_y_neg), cam.lim_y_pos);
  p.tx_free = rx >= -cam.lim_x_neg && rx <= cam.lim_x_pos;
  p.ty_free = ry >= -cam.lim_y_neg && ry <= cam.lim_y_pos;
  const double fx_z = cam.fx / p.z, fy_z = cam.fy / p.z;
  for (int k = 0; k < 3; ++k) {
    p.jw[0][k] = fx_z * (cam.rot[0][k] - p.tx * cam.rot[2][k]);
    p.jw[1][k] = fy_z * (cam.rot[1][k] - p.ty * cam.rot[2][k]);
  }

  const double qw = quat[0], qx = quat[1], qy = quat[2], qz = quat[3];
  const double n2 = qw * qw + qx * qx + qy * qy + qz * qz;
  p.norm_free = n2 >= kQuatEps2;
  p.inv_norm = 1.0 / std::sqrt(std::max(n2, kQuatEps2));
  const double w = qw * p.inv_norm, x = qx * p.inv_norm, y = qy * p.inv_norm, z = qz * p.inv_norm;
  p.qn[0] = w;
  p.qn[1] = x;
  p.qn[2] = y;
  p.qn[3] = z;
  p.rq[0][0] = 1 - 2 * (y * y + z * z);
  p.rq[0][1] = 2 * (x * y - w * z);
  p.rq[0][2] = 2 * (x * z + w * y);
  p.rq[1][0] = 2 * (x * y + w * z);
  p.rq[1][1] = 1 - 2 * (x * x + z * z);
  p.rq[1][2] = 2 * (y * z - w * x);
  p.rq[2][0] = 2 * (x * z - w * y);
  p.rq[2][1] = 2 * (y * z + w * x);
  p.rq[2][2] = 1 - 2 * (x * x + y * y);

  for (int i = 0; i < 2; ++i) {
    for (int j = 0; j < 3; ++j) {
      p.bmat[i][j] = p.jw[i][0] * p.rq[0][j] + p.jw[i][1] * p.rq[1][j] + p.jw[i][2] * p.rq[2][j];
      p.amat[i][j] = p.bmat[i][j] * static_cast<double>(scale[j]);
    }
  }
  const double (&am)[2][3] = p.amat;
  p.a = am[0][0] * am[0][0] + am[0][1] * am[0][1] + am[0][2] * am[0][2] + kLowPass;
  p.b = am[0][0] * am[1][0] + am[0][1] * am[1][1] + am[0][2] * am[1][2];
  p.c = am[1][0] * am[1][0] + am[1][1] * am[1][1] + am[1][2] * am[1][2] + kLowPass;
  p.finite = std::isfinite(p.a) && std::isfinite(p.b) && std::isfinite(p.c);
  if (!p.finite) {
    p.a = kLowPass;
    p.b = 0.0;
    p.c = kLowPass;
  }
  return p;
}

// One inclusive pixel-box axis [lo, hi] of the centres within `half` of `centre`, clipped to
// [0, size - 1]; returns whether it is non-empty (projection._pixel_box).
bool box_axis(double centre, double half, int size, int32_t* lo_out, int32_t* hi_out) {
  const double lo = std::ceil(centre - half), hi = std::floor(centre + half);
  const double top = size - 1.0;
  *lo_out = static_cast<int32_t>(std::min(std::max(lo, 0.0), top));
  *hi_out = static_cast<int32_t>(std::min(std::max(hi, 0.0), top));
  return lo <= hi && hi >= 0.0 && lo <= top;
}

template <typename scalar_t>
void project_forward_impl(const Camera& cam, int64_t n, const scalar_t* means, const scalar_t* quats,
                          const scalar_t* scales, const scalar_t* opacities, scalar_t* means2d,
                          scalar_t* conics, scalar_t* depths, int32_t* radii, int32_t* box, bool* visible) {
#pragma omp parallel for schedule(static)
  for (int64_t i = 0; i < n; ++i) {
    const Projected p = project_one(cam, means + 3 * i, quats + 4 * i, scales + 3 * i);
    const double det = p.a * p.c - p.b * p.b;
    means2d[2 * i] = static_cast<scalar_t>(p.u);
    means2d[2 * i + 1] = static_cast<scalar_t>(p.v);
    conics[3 * i] = static_cast<scalar_t>(p.c / det);
    conics[3 * i + 1] = static_cast<scalar_t>(-p.b / det);
    conics[3 * i + 2] = static_cast<scalar_t>(p.a / det);
    depths[i] = static_cast<scalar_t>(p.z);

    const double extent = std::sqrt(2.0 * std::log(std::max(static_cast<double>(opacities[i]) / kAlphaMin, 1.0)));
    const double half_x = extent * std::sqrt(p.a), half_y = extent * std::sqrt(p.c);
    int32_t* bx = box + 4 * i;
    bool nonempty = false;
    const bool centre_finite = std::isfinite(p.u) && std::isfinite(p.v);
    if (centre_finite) {
      const bool nx = box_axis(p.u, std::min(half_x, kMaxRadius), cam.width, bx, bx + 2);
      const bool ny = box_axis(p.v, std::min(half_y, kMaxRadius), cam.height, bx + 1, bx + 3);
      nonempty = nx && ny;
    } else {
      std::fill(bx, bx + 4, 0);
    }
    const bool vis = p.in_depth && p.finite && extent > 0.0 && nonempty && centre_finite;
    visible[i] = vis;
    radii[i] = vis ? static_cast<int32_t>(std::ceil(std::min(std::max(half_x, half_y), kMaxRadius))) : 0;
  }
}

// dL/d(qn) of the rotation entries, given dL/dR (3 x 3).
void rotation_vjp(const double qn[4], const double g[3][3], double out[4]) {
  const double w = qn[0], x = qn[1], y = qn[2], z = qn[3];
  out[0] = 2 * (-z * g[0][1] + y * g[0][2] + z * g[1][0] - x * g[1][2] - y * g[2][0] + x * g[2][1]);
  out[1] = 2 * (y * g[0][1] + z * g[0][2] + y * g[1][0] - 2 * x * g[1][1] - w * g[1][2] + z * g[2][0] +
                w * g[2][1] - 2 * x * g[2][2]);
  out[2] = 2 * (-2 * y * g[0][0] + x * g[0][1] + w * g[0][2] + x * g[1][0] + z * g[1][2] - w * g[2][0] +
                z * g[2][1] - 2 * y * g[2][2]);
  out[3] = 2 * (-2 * z * g[0][0] - w * g[0][1] + x * g[0][2] + w * g[1][0] - 2 * z * g[1][1] + y * g[1][2] +
                x * g[2][0] + y * g[2][1]);
}

template <typename scalar_t>
void project_backward_impl(const Camera& cam, int64_t n, const scalar_t* means, const scalar_t* quats,
                           const scalar_t* scales, const scalar_t* g_means2d, const scalar_t* g_conics,
                           const scalar_t* g_depths, scalar_t* g_means, scalar_t* g_quats, scalar_t* g_scales) {
#pragma omp parallel for schedule(static)
  for (int64_t i = 0; i < n; ++i) {
    const Projected p = project_one(cam, means + 3 * i, quats + 4 * i, scales + 3 * i);
    // Conic (c, -b, a) / det -> covariance entries a, b, c.
    double ga = 0.0, gb = 0.0, gc = 0.0;
    if (p.finite) {
      const double det = p.a * p.c - p.b * p.b, inv = 1.0 / det, inv2 = inv * inv;
      const double g0 = g_conics[3 * i], g1 = g_conics[3 * i + 1], g2 = g_conics[3 * i + 2];
      const double a = p.a, b = p.b, c = p.c;
      ga = -c * c * inv2 * g0 + b * c * inv2 * g1 - b * b * inv2 * g2;
      gb = 2 * b * c * inv2 * g0 + (-inv - 2 * b * b * inv2) * g1 + 2 * a * b * inv2 * g2;
      gc = -b * b * inv2 * g0 + a * b * inv2 * g1 - a * a * inv2 * g2;
    }
    double g_jw[2][3] = {}, g_rq[3][3] = {};
    for (int j = 0; j < 3; ++j) {
      const double d0 = 2 * ga * p.amat[0][j] + gb * p.amat[1][j];
      const double d1 = 2 * gc * p.amat[1][j] + gb * p.amat[0][j];
      g_scales[3 * i + j] = static_cast<scalar_t>(d0 * p.bmat[0][j] + d1 * p.bmat[1][j]);
      const double s = scales[3 * i + j];
      const double db[2] = {d0 * s, d1 * s};
      for (int k = 0; k < 3; ++k) {
        for (int r = 0; r < 2; ++r) {
          g_jw[r][k] += db[r] * p.rq[k][j];
          g_rq[k][j] += db[r] * p.jw[r][k];
        }
      }
    }
    double g_qn[4];
    rotation_vjp(p.qn, g_rq, g_qn);
    const double dot = p.norm_free ? p.qn[0] * g_qn[0] + p.qn[1] * g_qn[1] + p.qn[2] * g_qn[2] + p.qn[3] * g_qn[3]
                                   : 0.0;
    for (int k = 0; k < 4; ++k) g_quats[4 * i + k] = static_cast<scalar_t>(p.inv_norm * (g_qn[k] - p.qn[k] * dot));

    if (!p.in_depth) {  // the safe point is a constant
      for (int k = 0; k < 3; ++k) g_means[3 * i + k] = 0;
      continue;
    }
    const double x = p.x, y = p.y, z = p.z;
    double gx = 0.0, gy = 0.0, gz = static_cast<double>(g_depths[i]);
    double g_t[2] = {0.0, 0.0};
    const double f_z[2] = {cam.fx / z, cam.fy / z};
    for (int r = 0; r < 2; ++r) {
      for (int k = 0; k < 3; ++k) {
        gz -= g_jw[r][k] * p.jw[r][k] / z;
        g_t[r] -= g_jw[r][k] * f_z[r] * cam.rot[2][k];
      }
    }
    if (p.tx_free) {
      gx += g_t[0] / z;
      gz -= g_t[0] * x / (z * z);
    }
    if (p.ty_free) {
      gy += g_t[1] / z;
      gz -= g_t[1] * y / (z * z);
    }
    const double gu = g_means2d[2 * i], gv = g_means2d[2 * i + 1];
    gx += gu * cam.fx / z;
    gy += gv * cam.fy / z;
    gz -= (gu * cam.fx * x + gv * cam.fy * y) / (z * z);
    for (int k = 0; k < 3; ++k) {
      g_means[3 * i + k] = static_cast<scalar_t>(cam.rot[0][k] * gx + cam.rot[1][k] * gy + cam.rot[2][k] * gz);
    }
  }
}

// ---------------------------------------------------------------------------------------------
// Tile binning (tiling.py): per-tile lists, front to back (depth, then index, order).

// An inclusive rectangle of columns [x0, x1] and rows [y0, y1] (of pixels or of tiles).
struct Span {
  int x0, x1, y0, y1;
};

struct TileGrid {
  int tile_size, tiles_x, tiles_y, width, height;
  int num_tiles() const { return tiles_x * tiles_y; }
};

TileGrid make_grid(int64_t width, int64_t height, int64_t tile_size) {
  TORCH_CHECK(tile_size == 8 || tile_size == 16, "tile_size must be 8 or 16 (compiled sizes), got ", tile_size);
  const int ts = static_cast<int>(tile_size);
  return TileGrid{ts, static_cast<int>((width + ts - 1) / ts), static_cast<int>((height + ts - 1) / ts),
                  static_cast<int>(width), static_cast<int>(height)};
}

// Order-preserving unsigned key of a float's bits (negative values flipped, positive ones offset).
inline uint32_t sort_key(float x) {
  uint32_t bits;
  std::memcpy(&bits, &x, sizeof(bits));
  return bits ^ ((bits >> 31) != 0 ? 0xFFFFFFFFu : 0x80000000u);
}

inline uint64_t sort_key(double x) {
  uint64_t bits;
  std::memcpy(&bits, &x, sizeof(bits));
  return bits ^ ((bits >> 63) != 0 ? ~uint64_t{0} : uint64_t{1} << 63);
}

// The visible Gaussians by ascending depth, ties in index order: a stable LSD radix sort of the
// depth keys, 11 bits a pass, skipping passes whose digit is the same for every key.
template <typename scalar_t>
std::vector<int32_t> depth_order(int64_t n, const scalar_t* depths, const bool* visible) {
  using Key = decltype(sort_key(scalar_t{}));
  constexpr int kBits = 11, kBuckets = 1 << kBits;
  std::vector<int32_t> order, scratch;
  std::vector<Key> keys, scratch_keys;
  for (int64_t i = 0; i < n; ++i) {
    if (visible[i]) {
      order.push_back(static_cast<int32_t>(i));
      keys.push_back(sort_key(depths[i]));
    }
  }
  scratch.resize(order.size());
  scratch_keys.resize(keys.size());
  for (int shift = 0; shift < static_cast<int>(8 * sizeof(Key)); shift += kBits) {
    std::vector<int64_t> start(kBuckets + 1, 0);
    for (const Key key : keys) ++start[((key >> shift) & (kBuckets - 1)) + 1];
    if (std::any_of(start.begin() + 1, start.end(), [&](int64_t c) { return c == static_cast<int64_t>(keys.size()); })) {
      continue;
    }
    for (int b = 0; b < kBuckets; ++b) start[b + 1] += start[b];
    for (size_t i = 0; i < keys.size(); ++i) {
      const int64_t pos = start[(keys[i] >> shift) & (kBuckets - 1)]++;
      scratch[pos] = order[i];
      scratch_keys[pos] = keys[i];
    }
    order.swap(scratch);
    keys.swap(scratch_keys);
  }
  return order;
}

// Tile lists of the visible Gaussians: (order, ids, slots, tile_offsets, gauss_offsets) as
// documented in backend_cpu.TileBins. A list entry is the Gaussian's rank in `order`, so that a
// tile reads the packed Gaussians in increasing memory order.
template <typename scalar_t>
std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor> bin_tiles_impl(
    const TileGrid& grid, int64_t n, const int32_t* box, const scalar_t* depths, const bool* visible) {
  const int num_tiles = grid.num_tiles();
  const auto long_opts = at::TensorOptions().dtype(at::kLong);
  const auto int_opts = at::TensorOptions().dtype(at::kInt);
  // Box coordinates are pixels in [0, size - 1] and the tile size a power of two, so a shift divides
  // exactly (an integer division by the run-time tile size costs ~40 cycles on some CPUs).
  const int shift = __builtin_ctz(static_cast<unsigned>(grid.tile_size));
  // The tiles of Gaussian i: rows y0..y1, columns x0..x1 of the grid.
  auto tiles_of = [&](int64_t i) {
    const int32_t* b = box + 4 * i;
    return Span{b[0] >> shift, b[2] >> shift, b[1] >> shift, b[3] >> shift};
  };
  at::Tensor gauss_offsets = at::empty({n + 1}, long_opts);
  int64_t* goff = gauss_offsets.data_ptr<int64_t>();
  goff[0] = 0;
#pragma omp parallel for schedule(static)
  for (int64_t i = 0; i < n; ++i) {
    const Span t = tiles_of(i);
    goff[i + 1] = visible[i] ? static_cast<int64_t>(t.x1 - t.x0 + 1) * (t.y1 - t.y0 + 1) : 0;
  }
  for (int64_t i = 0; i < n; ++i) goff[i + 1] += goff[i];
  const int64_t pairs = goff[n];
  TORCH_CHECK(pairs <= std::numeric_limits<int32_t>::max(),
              pairs, " (Gaussian, tile) pairs overflow int32 indices; use a larger tile size");

  const std::vector<int32_t> sorted = depth_order(n, depths, visible);
  const int64_t num_visible = static_cast<int64_t>(sorted.size());
  at::Tensor order = at::empty({num_visible}, int_opts);
  std::copy(sorted.begin(), sorted.end(), order.data_ptr<int32_t>());

  // The tiles and first slot of each rank, gathered once in a loop of independent loads: read in the
  // branchy tile loops below through `sorted`, each random box read waited for its cache miss in turn.
  struct RankTiles {
    Span tiles;
    int32_t slot;
  };
  std::vector<RankTiles> by_rank(static_cast<size_t>(num_visible));
#pragma omp parallel for schedule(static)
  for (int64_t rank = 0; rank < num_visible; ++rank) {
    const int32_t g = sorted[rank];
    by_rank[rank] = RankTiles{tiles_of(g), static_cast<int32_t>(goff[g])};
  }

  // Fixed chunks of consecutive ranks count their pairs per tile, then fill their part of every
  // tile's list in parallel: chunk c writes after chunks < c, so lists stay in rank order.
  const int64_t chunks = std::clamp<int64_t>(num_visible / 4096, 1, 64);
  auto chunk_begin = [&](int64_t c) { return num_visible * c / chunks; };
  std::vector<int64_t> cursor(static_cast<size_t>(chunks) * num_tiles, 0);
#pragma omp parallel for schedule(static)
  for (int64_t c = 0; c < chunks; ++c) {
    int64_t* count = cursor.data() + c * num_tiles;
    const int64_t rank_end = chunk_begin(c + 1);  // a local: the loop's stores may alias captured values
    for (int64_t rank = chunk_begin(c); rank < rank_end; ++rank) {
      const Span t = by_rank[rank].tiles;
      for (int ty = t.y0; ty <= t.y1; ++ty) {
        for (int tx = t.x0; tx <= t.x1; ++tx) ++count[ty * grid.tiles_x + tx];
      }
    }
  }
  at::Tensor tile_offsets = at::empty({num_tiles + 1}, long_opts);
  int64_t* toff = tile_offsets.data_ptr<int64_t>();
  int64_t running = 0;
  for (int t = 0; t < num_tiles; ++t) {
    toff[t] = running;
    for (int64_t c = 0; c < chunks; ++c) {
      const int64_t count = cursor[c * num_tiles + t];
      cursor[c * num_tiles + t] = running;
      running += count;
    }
  }
  toff[num_tiles] = running;

  at::Tensor ids = at::empty({pairs}, int_opts), slots = at::empty({pairs}, int_opts);
  int32_t* id_p = ids.data_ptr<int32_t>();
  int32_t* slot_p = slots.data_ptr<int32_t>();
#pragma omp parallel for schedule(static)
  for (int64_t c = 0; c < chunks; ++c) {
    int64_t* next = cursor.data() + c * num_tiles;
    const int64_t rank_end = chunk_begin(c + 1);  // a local: the loop's stores may alias captured values
    for (int64_t rank = chunk_begin(c); rank < rank_end; ++rank) {
      const Span t = by_rank[rank].tiles;
      int32_t slot = by_rank[rank].slot;
      for (int ty = t.y0; ty <= t.y1; ++ty) {
        for (int tx = t.x0; tx <= t.x1; ++tx) {
          const int64_t pos = next[ty * grid.tiles_x + tx]++;
          id_p[pos] = static_cast<int32_t>(rank);
          slot_p[pos] = slot++;
        }
      }
    }
  }
  return {order, ids, slots, tile_offsets, gauss_offsets};
}

// ---------------------------------------------------------------------------------------------
// Compositing (compositing.py), one tile at a time. The pixel loops run over whole tile rows in
// 32-byte vectors (GCC vector extensions: 8 floats or 4 doubles per vector, AVX2 on x86) with
// per-lane masks; every lane does the same IEEE operations a scalar loop would.

template <typename scalar_t>
struct Simd;

template <>
struct Simd<float> {
  typedef float V __attribute__((vector_size(32)));
  typedef int32_t I __attribute__((vector_size(32)));
  static constexpr int kLanes = 8;
  static constexpr float kExp2Floor = -115.0f;  // 2^-115 = 2.4e-35, clear of subnormals
  static constexpr float kRound = 12582912.0f;  // 1.5 * 2^23: x + kRound - kRound rounds x to an integer
  static constexpr int32_t kRoundBits = 0x4B400000;
  static constexpr int kMantissa = 23, kBias = 127, kTaylor = 6;
  // ln(2)^k / k! for k = 0, 1, ..., 6: the Taylor polynomial of 2^r = exp(r ln 2)
  static constexpr float kTaylorCoef[kTaylor + 1] = {1.0f, 0.6931471805599453f, 0.2402265069591007f,
                                                     0.055504108664821576f, 0.009618129107628477f,
                                                     0.0013333558146428441f, 0.00015403530393381606f};
};

template <>
struct Simd<double> {
  typedef double V __attribute__((vector_size(32)));
  typedef int64_t I __attribute__((vector_size(32)));
  static constexpr int kLanes = 4;
  static constexpr double kExp2Floor = -1000.0;  // 2^-1000 = 9.3e-302
  static constexpr double kRound = 6755399441055744.0;  // 1.5 * 2^52
  static constexpr int64_t kRoundBits = 0x4338000000000000LL;
  static constexpr int kMantissa = 52, kBias = 1023, kTaylor = 12;
  // ln(2)^k / k! for k = 0, 1, ..., 12
  static constexpr double kTaylorCoef[kTaylor + 1] = {
      1.0,                  0.6931471805599453,    0.2402265069591007,    0.055504108664821576,
      0.009618129107628477, 0.0013333558146428441, 0.00015403530393381606, 1.5252733804059838e-05,
      1.3215486790144305e-06, 1.0178086009239696e-07, 7.054911620801121e-09, 4.44553827187081e-10,
      2.5678435993488196e-11};
};

// 2^x for x <= 0 per lane: x = n + r with n an integer and |r| <= 1/2 (n rounded by the
// 1.5 * 2^mantissa trick; r = x - n is exact), a Taylor polynomial for 2^r of degree 6 (float,
// relative error 1.2e-7) or 12 (double, 2e-16) and 2^n written into the exponent bits. Below
// x = -115 (float) or -1000 (double) it returns 2 to that limit: alpha is far below ALPHA_MIN
// there, and the limit keeps it clear of subnormal numbers, whose arithmetic is ~100x slower.
// Working in base 2 (the conic and the opacity folded into x, see RowTerms) saves the ln 2 range
// reduction of exp and the multiplication by the opacity: 6 of the ~66 vector operations per 8
// pixels of the forward.
template <typename scalar_t>
inline typename Simd<scalar_t>::V exp2_neg(typename Simd<scalar_t>::V x) {
  using S = Simd<scalar_t>;
  using V = typename S::V;
  using I = typename S::I;
  x = x < S::kExp2Floor ? V{} + S::kExp2Floor : x;
  const V t = x + S::kRound;
  const V n = t - S::kRound;
  const V r = x - n;
  // Estrin's scheme: pairs c_2j + c_2j+1 r, then pairs of those with r^2, r^4, ...: a dependency
  // chain of ~log2(degree) multiply-adds instead of Horner's degree.
  constexpr int kTerms = S::kTaylor / 2 + 1;
  V terms[kTerms];
  for (int j = 0; j < kTerms; ++j) {
    terms[j] = 2 * j + 1 <= S::kTaylor ? S::kTaylorCoef[2 * j] + S::kTaylorCoef[2 * j + 1] * r
                                       : V{} + S::kTaylorCoef[2 * j];
  }
  V power = r * r;
  for (int count = kTerms; count > 1; count = (count + 1) / 2, power = power * power) {
    for (int j = 0; 2 * j < count; ++j) terms[j] = 2 * j + 1 < count ? terms[2 * j] + power * terms[2 * j + 1] : terms[2 * j];
  }
  const V p = terms[0];
  // Vector casts between same-size vector types reinterpret the bits.
  const I bits = (((I)t - S::kRoundBits) + S::kBias) << S::kMantissa;
  return p * (V)bits;
}

// A Gaussian's screen-space parameters and pixel box, packed for the pixel loops (one or two
// cache lines). Tile lists jump through them, so the loops prefetch kPrefetch entries ahead.
constexpr int kPrefetch = 8;

template <typename scalar_t>
struct alignas(64) Splat {
  scalar_t mx, my, a, b, c, opacity, log2_opacity;
  scalar_t color[3];
  scalar_t depth;
  int32_t box[4];
};

// A buffer of the calling thread that keeps its memory from call to call (one per element type and use,
// never shrinking): a 200k-Gaussian backward writes ~35 MB of per-pair gradients, and faulting in fresh
// zeroed pages on every call cost about as much as the compositing. Not initialised: callers write every
// element they read.
enum class Buffer { kSplats, kPairGrad };

template <typename T, Buffer kUse>
T* reusable_buffer(size_t n) {
  static thread_local std::vector<T> buffer;
  if (buffer.size() < n) buffer.resize(n);
  return buffer.data();
}

// The Gaussians of `order` (depth order, see bin_tiles_impl), packed into this thread's splat buffer.
template <typename scalar_t>
const Splat<scalar_t>* pack_splats(const at::Tensor& order, const scalar_t* means2d, const scalar_t* conics,
                                   const scalar_t* opacities, const scalar_t* colors, const scalar_t* depths,
                                   const int32_t* box) {
  const int64_t n = order.size(0);
  const int32_t* ord = order.const_data_ptr<int32_t>();
  Splat<scalar_t>* splats = reusable_buffer<Splat<scalar_t>, Buffer::kSplats>(static_cast<size_t>(n));
#pragma omp parallel for schedule(static)
  for (int64_t r = 0; r < n; ++r) {
    const int64_t i = ord[r];
    const scalar_t log2_o = static_cast<scalar_t>(std::log2(static_cast<double>(opacities[i])));
    splats[r] = Splat<scalar_t>{means2d[2 * i], means2d[2 * i + 1], conics[3 * i], conics[3 * i + 1],
                                conics[3 * i + 2], opacities[i], log2_o,
                                {colors[3 * i], colors[3 * i + 1], colors[3 * i + 2]},
                                depths[i], {box[4 * i], box[4 * i + 1], box[4 * i + 2], box[4 * i + 3]}};
  }
  return splats;
}

// The unclamped alpha o exp(-q / 2) = 2^(log2 o - q log2(e) / 2) of a Gaussian at pixel offsets
// (dx, dy) from its mean. The forward and the backward both call it, so their skip and clamp
// decisions agree bit for bit.
//   -q log2(e) / 2 = (k a dx + 2 k b dy) dx + k c dy^2 with k = -log2(e) / 2, the row terms per row.
template <typename scalar_t>
struct RowTerms {
  static constexpr scalar_t kMinusHalfLog2e = static_cast<scalar_t>(-0.72134752044448170368);  // -log2(e) / 2
  scalar_t dy, ka, kb2dy, kcdy2_log2o;
  RowTerms(const Splat<scalar_t>& s, int y)
      : dy(static_cast<scalar_t>(y) - s.my), ka(kMinusHalfLog2e * s.a), kb2dy(2 * kMinusHalfLog2e * s.b * dy),
        kcdy2_log2o(kMinusHalfLog2e * s.c * dy * dy + s.log2_opacity) {}
};

template <typename scalar_t>
inline typename Simd<scalar_t>::V raw_alpha(typename Simd<scalar_t>::V dx, const RowTerms<scalar_t>& row) {
  return exp2_neg<scalar_t>((row.ka * dx + row.kb2dy) * dx + row.kcdy2_log2o);
}

struct TileRect {
  int x0, y0, w, h;
  Span clip(const int32_t* b) const {
    return Span{std::max<int>(b[0] - x0, 0), std::min<int>(b[2] - x0, w - 1), std::max<int>(b[1] - y0, 0),
                std::min<int>(b[3] - y0, h - 1)};
  }
};

inline TileRect tile_rect(const TileGrid& grid, int t) {
  const int x0 = (t % grid.tiles_x) * grid.tile_size, y0 = (t / grid.tiles_x) * grid.tile_size;
  return TileRect{x0, y0, std::min(grid.tile_size, grid.width - x0), std::min(grid.tile_size, grid.height - y0)};
}

// Runs `body(tile)` over all tiles on the OpenMP threads, handing out tiles dynamically.
template <typename Body>
void for_each_tile(const TileGrid& grid, Body body) {
  std::atomic<int> next{0};
#pragma omp parallel
  {
    for (int t = next.fetch_add(1); t < grid.num_tiles(); t = next.fetch_add(1)) body(t);
  }
}

// Pixel columns of a tile row as vectors, and masks of columns as bit sets (bit j: column j).
template <typename scalar_t, int TS>
struct RowLanes {
  using S = Simd<scalar_t>;
  using I = typename S::I;
  static_assert(TS % S::kLanes == 0 && TS <= 16, "tile rows are whole vectors, at most 16 pixels");
  static constexpr int kChunks = TS / S::kLanes;
  static constexpr uint32_t kChunkBits = (1u << S::kLanes) - 1;
  I bit;                       // lane l: 1 << l
  typename S::V x[kChunks];    // pixel x coordinates of chunk c
  explicit RowLanes(int x0) {
    for (int l = 0; l < S::kLanes; ++l) {
      bit[l] = 1 << l;
      for (int c = 0; c < kChunks; ++c) x[c][l] = static_cast<scalar_t>(x0 + c * S::kLanes + l);
    }
  }
  // Columns [x0, x1] as a bit set.
  static uint32_t columns(int x0, int x1) { return ((2u << x1) - 1) & ~((1u << x0) - 1); }
  // The lanes of chunk c in a row bit set, as a lane mask, and their bits.
  static uint32_t chunk_bits(uint32_t row_bits, int c) { return (row_bits >> (c * S::kLanes)) & kChunkBits; }
  I mask(uint32_t bits) const { return ((I{} + static_cast<typename std::remove_reference_t<decltype(bit[0])>>(bits)) & bit) != 0; }
  // The bit set of a lane mask's set lanes (one instruction with AVX).
  static uint32_t bits_of(I mask) {
#if defined(__AVX__)
    if constexpr (S::kLanes == 8) {
      return static_cast<uint32_t>(_mm256_movemask_ps((__m256)mask));
    } else {
      return static_cast<uint32_t>(_mm256_movemask_pd((__m256d)mask));
    }
#else
    uint32_t out = 0;
    for (int l = 0; l < S::kLanes; ++l) out |= static_cast<uint32_t>(mask[l] & 1) << l;
    return out;
#endif
  }
};

// Sum of a vector's lanes by halving (a fixed order, so the result is reproducible).
inline float lane_sum(Simd<float>::V v) {
  v += __builtin_shufflevector(v, v, 4, 5, 6, 7, 0, 1, 2, 3);
  v += __builtin_shufflevector(v, v, 2, 3, 0, 1, 6, 7, 4, 5);
  v += __builtin_shufflevector(v, v, 1, 0, 3, 2, 5, 4, 7, 6);
  return v[0];
}

inline double lane_sum(Simd<double>::V v) {
  v += __builtin_shufflevector(v, v, 2, 3, 0, 1);
  v += __builtin_shufflevector(v, v, 1, 0, 3, 2);
  return v[0];
}

// Counters of the forward pass, for the benchmark: alpha evaluations (pixels of a Gaussian's box
// in a tile that have not stopped) and contributing (Gaussian, pixel) pairs.
struct Counts {
  int64_t evaluations = 0, contributions = 0;
};

template <typename scalar_t, int TS, bool kCount>
void raster_forward_impl(const TileGrid& grid, const Splat<scalar_t>* splats, const int32_t* ids,
                         const int64_t* toff, const scalar_t* background, scalar_t* rgb, scalar_t* alpha_out,
                         scalar_t* depth_out, scalar_t* t_final, int32_t* last_out, int16_t* kept_rows,
                         std::vector<Counts>* counts) {
  using S = Simd<scalar_t>;
  using V = typename S::V;
  using I = typename S::I;
  using Lanes = RowLanes<scalar_t, TS>;
  constexpr int L = S::kLanes, kVecs = TS * TS / L;
  for_each_tile(grid, [&](int t) {
    const TileRect r = tile_rect(grid, t);
    const Lanes lanes(r.x0);
    V trans[kVecs], acc[kVecs], f0[kVecs], f1[kVecs], f2[kVecs], f3[kVecs];
    I last[kVecs];
    uint32_t done[TS];  // stopped pixels per row; the padding of border tiles starts stopped
    for (int v = 0; v < kVecs; ++v) {
      trans[v] = V{} + 1;
      acc[v] = f0[v] = f1[v] = f2[v] = f3[v] = V{};
      last[v] = I{} - 1;
    }
    for (int row = 0; row < TS; ++row) done[row] = row < r.h ? ~Lanes::columns(0, r.w - 1) : ~0u;
    int remaining = r.w * r.h;
    Counts local;
    const int64_t begin = toff[t], end = toff[t + 1];
    for (int64_t k = begin; k < end && remaining > 0; ++k) {
      if (k + kPrefetch < end) __builtin_prefetch(&splats[ids[k + kPrefetch]]);
      const Splat<scalar_t>& s = splats[ids[k]];
      const Span sp = r.clip(s.box);
      const uint32_t span = Lanes::columns(sp.x0, sp.x1);
      const I kk = I{} + static_cast<int32_t>(k - begin);
      uint32_t rows_kept = 0;
      for (int row = sp.y0; row <= sp.y1; ++row) {
        const uint32_t open_row = span & ~done[row];
        if (open_row == 0) continue;
        const RowTerms<scalar_t> terms(s, r.y0 + row);
        I row_keep{};
        for (int c = 0; c < Lanes::kChunks; ++c) {
          const uint32_t open_bits = Lanes::chunk_bits(open_row, c);
          if (open_bits == 0) continue;
          const int v = row * Lanes::kChunks + c;
          const V raw = raw_alpha<scalar_t>(lanes.x[c] - s.mx, terms);
          const I hit = lanes.mask(open_bits) & (raw >= static_cast<scalar_t>(kAlphaMin));
          // Missed lanes get alpha 0: no subnormal products, T unchanged.
          const V alpha = hit ? (raw < static_cast<scalar_t>(kAlphaMax) ? raw : V{} + static_cast<scalar_t>(kAlphaMax))
                              : V{};
          const V next = trans[v] * (1 - alpha);
          const I stop = hit & (next < static_cast<scalar_t>(kTMin));
          const I keep = hit & ~stop;
          const V w = keep ? alpha * trans[v] : V{};
          f0[v] += w * s.color[0];
          f1[v] += w * s.color[1];
          f2[v] += w * s.color[2];
          f3[v] += w * s.depth;
          acc[v] += w;
          trans[v] = keep ? next : trans[v];
          last[v] = keep ? kk : last[v];
          row_keep |= keep;
          const uint32_t stop_bits = Lanes::bits_of(stop);
          if (stop_bits != 0) {
            done[row] |= stop_bits << (c * L);
            remaining -= __builtin_popcount(stop_bits);
          }
          if (kCount) {
            local.evaluations += __builtin_popcount(open_bits);
            local.contributions += __builtin_popcount(Lanes::bits_of(keep));
          }
        }
        if (Lanes::bits_of(row_keep) != 0) rows_kept |= 1u << row;
      }
      kept_rows[k] = static_cast<int16_t>(rows_kept);
    }
    for (int iy = 0; iy < r.h; ++iy) {
      for (int ix = 0; ix < r.w; ++ix) {
        const int v = iy * Lanes::kChunks + ix / L, l = ix % L;
        const int64_t o = static_cast<int64_t>(r.y0 + iy) * grid.width + r.x0 + ix;
        const scalar_t a = acc[v][l];
        rgb[3 * o] = f0[v][l] + (1 - a) * background[0];
        rgb[3 * o + 1] = f1[v][l] + (1 - a) * background[1];
        rgb[3 * o + 2] = f2[v][l] + (1 - a) * background[2];
        alpha_out[o] = a;
        depth_out[o] = f3[v][l];
        t_final[o] = trans[v][l];
        last_out[o] = static_cast<int32_t>(last[v][l]);
      }
    }
    if (kCount) (*counts)[t] = local;
  });
}

template <typename scalar_t, int TS>
void raster_backward_impl(const TileGrid& grid, const Splat<scalar_t>* splats, const int32_t* ids,
                          const int32_t* slots, const int16_t* kept_rows, const int64_t* toff,
                          const scalar_t* background,
                          const scalar_t* alpha_in, const scalar_t* t_final, const int32_t* last_in,
                          const scalar_t* g_rgb, const scalar_t* g_alpha, const scalar_t* g_depth,
                          scalar_t* pair_grad, double* tile_bg_grad) {
  using S = Simd<scalar_t>;
  using V = typename S::V;
  using I = typename S::I;
  using Lanes = RowLanes<scalar_t, TS>;
  constexpr int L = S::kLanes, kVecs = TS * TS / L;
  for_each_tile(grid, [&](int t) {
    const TileRect r = tile_rect(grid, t);
    const Lanes lanes(r.x0);
    V trans[kVecs], later[kVecs], g0[kVecs], g1[kVecs], g2[kVecs], g3[kVecs], g_acc[kVecs];
    I last[kVecs];
    int32_t chunk_last[kVecs];  // the largest last contributor of each chunk's pixels
    for (int v = 0; v < kVecs; ++v) {
      trans[v] = later[v] = g0[v] = g1[v] = g2[v] = g3[v] = g_acc[v] = V{};
      last[v] = I{} - 1;  // padding pixels: nothing to replay
      chunk_last[v] = -1;
    }
    int32_t max_last = -1;
    double bg[3] = {0.0, 0.0, 0.0};
    for (int iy = 0; iy < r.h; ++iy) {
      for (int ix = 0; ix < r.w; ++ix) {
        const int v = iy * Lanes::kChunks + ix / L, l = ix % L;
        const int64_t o = static_cast<int64_t>(r.y0 + iy) * grid.width + r.x0 + ix;
        const scalar_t* gr = g_rgb + 3 * o;
        trans[v][l] = t_final[o];
        last[v][l] = last_in[o];
        chunk_last[v] = std::max(chunk_last[v], last_in[o]);
        max_last = std::max(max_last, last_in[o]);
        g0[v][l] = gr[0];
        g1[v][l] = gr[1];
        g2[v][l] = gr[2];
        g3[v][l] = g_depth[o];
        // rgb = feat + (1 - acc) background and alpha = acc: dL/dacc gathers both.
        g_acc[v][l] = g_alpha[o] - (background[0] * gr[0] + background[1] * gr[1] + background[2] * gr[2]);
        for (int ch = 0; ch < 3; ++ch) bg[ch] += static_cast<double>((1 - alpha_in[o]) * gr[ch]);
      }
    }
    for (int ch = 0; ch < 3; ++ch) tile_bg_grad[3 * t + ch] = bg[ch];
    const int64_t begin = toff[t], end = toff[t + 1];
    auto zero_pair = [&](int64_t k) {
      std::fill_n(pair_grad + int64_t{kPairGrad} * slots[k], kPairGrad, scalar_t(0));
    };
    for (int64_t k = begin + max_last + 1; k < end; ++k) zero_pair(k);
    for (int64_t k = begin + max_last; k >= begin; --k) {
      // Rows where the forward blended nothing of pair k replay nothing (a pixel replays k only if the
      // forward kept it there), so they are skipped: the gradients are those of the full replay, bit for bit.
      const uint32_t rows = static_cast<uint16_t>(kept_rows[k]);
      if (rows == 0) {
        zero_pair(k);
        continue;
      }
      if (k - kPrefetch >= begin) __builtin_prefetch(&splats[ids[k - kPrefetch]]);
      const int32_t local_k = static_cast<int32_t>(k - begin);
      const I kk = I{} + local_k;
      const Splat<scalar_t>& s = splats[ids[k]];
      const Span sp = r.clip(s.box);
      const uint32_t span = Lanes::columns(sp.x0, sp.x1);
      I span_mask[Lanes::kChunks];
      for (int c = 0; c < Lanes::kChunks; ++c) span_mask[c] = lanes.mask(Lanes::chunk_bits(span, c));
      // With p = alpha dL/dalpha per pixel (dL/dq = -p / 2) the conic and mean gradients are moments of p:
      //   dL/da = -sum(p dx^2) / 2, dL/db = -sum(p dx dy), dL/dc = -sum(p dy^2) / 2,
      //   dL/dmx = a sum(p dx) + b sum(p dy), dL/dmy = b sum(p dx) + c sum(p dy), dL/do = sum(p) / o.
      // dy is constant along a row, so a row sums p and p dx over its chunks and multiplies by dy once.
      V m_1{}, m_x{}, m_y{}, m_xx{}, m_xy{}, m_yy{}, g_r{}, g_g{}, g_b{}, g_d{};
      for (int row = sp.y0; row <= sp.y1; ++row) {
        if (((rows >> row) & 1u) == 0) continue;
        const RowTerms<scalar_t> terms(s, r.y0 + row);
        V row_p{}, row_px{};
        for (int c = 0; c < Lanes::kChunks; ++c) {
          const int v = row * Lanes::kChunks + c;
          if (Lanes::chunk_bits(span, c) == 0 || local_k > chunk_last[v]) continue;  // no pixel of the chunk replays k
          const V dx = lanes.x[c] - s.mx;
          const V raw = raw_alpha<scalar_t>(dx, terms);
          const I hit = span_mask[c] & (kk <= last[v]) & (raw >= static_cast<scalar_t>(kAlphaMin));
          const I free = hit & (raw < static_cast<scalar_t>(kAlphaMax));  // alpha not clamped
          // Missed lanes get alpha 0: w = 0, and T and the later sum stay as they are.
          const V alpha = hit ? (raw < static_cast<scalar_t>(kAlphaMax) ? raw : V{} + static_cast<scalar_t>(kAlphaMax))
                              : V{};
          const V inv_one_minus = 1 / (1 - alpha);
          const V t_prev = trans[v] * inv_one_minus;
          const V w = alpha * t_prev;
          const V val = s.color[0] * g0[v] + s.color[1] * g1[v] + s.color[2] * g2[v] + s.depth * g3[v] + g_acc[v];
          // dL/dalpha = T_prev v - (sum over later Gaussians of w v) / (1 - alpha), 0 where clamped.
          const V d_alpha = free ? t_prev * val - later[v] * inv_one_minus : V{};
          later[v] = hit ? later[v] + w * val : later[v];
          trans[v] = hit ? t_prev : trans[v];
          g_r += w * g0[v];
          g_g += w * g1[v];
          g_b += w * g2[v];
          g_d += w * g3[v];
          const V p = raw * d_alpha;  // alpha dL/dalpha: raw is alpha wherever d_alpha is not 0
          const V p_dx = p * dx;
          row_p += p;
          row_px += p_dx;
          m_xx += p_dx * dx;
        }
        const scalar_t dy = terms.dy;
        m_1 += row_p;
        m_x += row_px;
        m_y += dy * row_p;
        m_xy += dy * row_px;
        m_yy += (dy * dy) * row_p;
      }
      const double p1 = lane_sum(m_1), px = lane_sum(m_x), py = lane_sum(m_y);
      const double pxx = lane_sum(m_xx), pxy = lane_sum(m_xy), pyy = lane_sum(m_yy);
      const double a = s.a, b = s.b, c = s.c, o = s.opacity;
      scalar_t* out = pair_grad + int64_t{kPairGrad} * slots[k];
      out[0] = static_cast<scalar_t>(a * px + b * py);
      out[1] = static_cast<scalar_t>(b * px + c * py);
      out[2] = static_cast<scalar_t>(-0.5 * pxx);
      out[3] = static_cast<scalar_t>(-pxy);
      out[4] = static_cast<scalar_t>(-0.5 * pyy);
      out[5] = static_cast<scalar_t>(o > 0 ? p1 / o : 0.0);
      out[6] = lane_sum(g_r);
      out[7] = lane_sum(g_g);
      out[8] = lane_sum(g_b);
      out[9] = lane_sum(g_d);
    }
  });
}

// ---------------------------------------------------------------------------------------------
// Operators

void set_threads(int64_t threads) {
  TORCH_CHECK(threads >= 1, "threads must be >= 1");
  omp_set_num_threads(static_cast<int>(threads));
}

void check_cpu(const at::Tensor& t, const char* name) {
  TORCH_CHECK(t.device().is_cpu(), name, " must be a CPU tensor");
}

std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor> project_forward(
    const at::Tensor& means, const at::Tensor& quats, const at::Tensor& scales, const at::Tensor& opacities,
    const at::Tensor& K, const at::Tensor& view, int64_t width, int64_t height, double near_plane,
    double far_plane, int64_t threads) {
  check_cpu(means, "means");
  set_threads(threads);
  const Camera cam = make_camera(K, view, width, height, near_plane, far_plane);
  const int64_t n = means.size(0);
  const auto opts = means.options();
  at::Tensor means2d = at::empty({n, 2}, opts), conics = at::empty({n, 3}, opts), depths = at::empty({n}, opts);
  at::Tensor radii = at::empty({n}, opts.dtype(at::kInt)), box = at::empty({n, 4}, opts.dtype(at::kInt));
  at::Tensor visible = at::empty({n}, opts.dtype(at::kBool));
  const at::Tensor m = means.contiguous(), q = quats.contiguous(), s = scales.contiguous(), o = opacities.contiguous();
  auto run = [&](auto tag) {
    using scalar_t = decltype(tag);
    project_forward_impl<scalar_t>(cam, n, m.const_data_ptr<scalar_t>(), q.const_data_ptr<scalar_t>(),
                                   s.const_data_ptr<scalar_t>(), o.const_data_ptr<scalar_t>(),
                                   means2d.data_ptr<scalar_t>(), conics.data_ptr<scalar_t>(),
                                   depths.data_ptr<scalar_t>(), radii.data_ptr<int32_t>(), box.data_ptr<int32_t>(),
                                   visible.data_ptr<bool>());
  };
  if (means.scalar_type() == at::kDouble) run(double{}); else run(float{});
  return {means2d, conics, depths, radii, box, visible};
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> project_backward(
    const at::Tensor& means, const at::Tensor& quats, const at::Tensor& scales, const at::Tensor& K,
    const at::Tensor& view, int64_t width, int64_t height, double near_plane, double far_plane,
    const at::Tensor& g_means2d, const at::Tensor& g_conics, const at::Tensor& g_depths, int64_t threads) {
  set_threads(threads);
  const Camera cam = make_camera(K, view, width, height, near_plane, far_plane);
  const int64_t n = means.size(0);
  at::Tensor g_means = at::empty({n, 3}, means.options()), g_quats = at::empty({n, 4}, means.options());
  at::Tensor g_scales = at::empty({n, 3}, means.options());
  const at::Tensor m = means.contiguous(), q = quats.contiguous(), s = scales.contiguous();
  const at::Tensor gm = g_means2d.contiguous(), gc = g_conics.contiguous(), gd = g_depths.contiguous();
  auto run = [&](auto tag) {
    using scalar_t = decltype(tag);
    project_backward_impl<scalar_t>(cam, n, m.const_data_ptr<scalar_t>(), q.const_data_ptr<scalar_t>(),
                                    s.const_data_ptr<scalar_t>(), gm.const_data_ptr<scalar_t>(),
                                    gc.const_data_ptr<scalar_t>(), gd.const_data_ptr<scalar_t>(),
                                    g_means.data_ptr<scalar_t>(), g_quats.data_ptr<scalar_t>(),
                                    g_scales.data_ptr<scalar_t>());
  };
  if (means.scalar_type() == at::kDouble) run(double{}); else run(float{});
  return {g_means, g_quats, g_scales};
}

std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor> bin_tiles(
    const at::Tensor& box, const at::Tensor& depths, const at::Tensor& visible, int64_t width, int64_t height,
    int64_t tile_size, int64_t threads) {
  set_threads(threads);
  const TileGrid grid = make_grid(width, height, tile_size);
  const at::Tensor b = box.contiguous(), d = depths.contiguous(), v = visible.contiguous();
  const int64_t n = b.size(0);
  if (d.scalar_type() == at::kDouble) {
    return bin_tiles_impl<double>(grid, n, b.const_data_ptr<int32_t>(), d.const_data_ptr<double>(),
                                  v.const_data_ptr<bool>());
  }
  return bin_tiles_impl<float>(grid, n, b.const_data_ptr<int32_t>(), d.const_data_ptr<float>(),
                               v.const_data_ptr<bool>());
}

// Calls f(scalar_t{}, std::integral_constant<int, tile size>{}) for the compiled dtypes and tile sizes.
template <typename F>
void dispatch(at::ScalarType dtype, int tile_size, F f) {
  TORCH_CHECK(dtype == at::kFloat || dtype == at::kDouble, "the cpu rasterizer takes float32 or float64, got ",
              dtype);
  auto with_tile = [&](auto tag) {
    if (tile_size == 8) {
      f(tag, std::integral_constant<int, 8>{});
    } else {
      f(tag, std::integral_constant<int, 16>{});
    }
  };
  if (dtype == at::kDouble) {
    with_tile(double{});
  } else {
    with_tile(float{});
  }
}

// The Gaussians and tile lists both compositing passes read, made contiguous once.
struct RasterInputs {
  at::Tensor means2d, conics, opacities, colors, depths, background, box, order, ids, tile_offsets;
  TileGrid grid;
  RasterInputs(const at::Tensor& m, const at::Tensor& c, const at::Tensor& o, const at::Tensor& col,
               const at::Tensor& d, const at::Tensor& bg, const at::Tensor& b, const at::Tensor& ord,
               const at::Tensor& i, const at::Tensor& t, int64_t width, int64_t height, int64_t tile_size)
      : means2d(m.contiguous()), conics(c.contiguous()), opacities(o.contiguous()), colors(col.contiguous()),
        depths(d.contiguous()), background(bg.contiguous()), box(b.contiguous()), order(ord.contiguous()),
        ids(i.contiguous()), tile_offsets(t.contiguous()), grid(make_grid(width, height, tile_size)) {
    TORCH_CHECK(colors.size(1) == 3, "colors must be (N, 3)");
  }
  template <typename scalar_t>
  const Splat<scalar_t>* splats() const {
    return pack_splats<scalar_t>(order, means2d.const_data_ptr<scalar_t>(), conics.const_data_ptr<scalar_t>(),
                                 opacities.const_data_ptr<scalar_t>(), colors.const_data_ptr<scalar_t>(),
                                 depths.const_data_ptr<scalar_t>(), box.const_data_ptr<int32_t>());
  }
};

// The forward pass: (rgb, alpha, depth, t_final, last, kept_rows); kept_rows (P,) int16: bit r of pair k is
// set when the forward blended Gaussian k into a pixel of row r of its tile (0 for pairs after the tile stopped).
template <bool kCount>
std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor> forward_pass(
    const RasterInputs& in, std::vector<Counts>* counts) {
  const auto opts = in.means2d.options();
  const int64_t h = in.grid.height, w = in.grid.width;
  at::Tensor rgb = at::empty({h, w, 3}, opts), alpha = at::empty({h, w}, opts), depth = at::empty({h, w}, opts);
  at::Tensor t_final = at::empty({h, w}, opts), last = at::empty({h, w}, opts.dtype(at::kInt));
  at::Tensor kept_rows = at::empty({in.ids.size(0)}, opts.dtype(at::kShort));
  std::fill_n(kept_rows.data_ptr<int16_t>(), kept_rows.numel(), int16_t{0});
  dispatch(in.means2d.scalar_type(), in.grid.tile_size, [&](auto tag, auto tile) {
    using scalar_t = decltype(tag);
    raster_forward_impl<scalar_t, decltype(tile)::value, kCount>(
        in.grid, in.splats<scalar_t>(), in.ids.const_data_ptr<int32_t>(), in.tile_offsets.const_data_ptr<int64_t>(),
        in.background.const_data_ptr<scalar_t>(), rgb.data_ptr<scalar_t>(), alpha.data_ptr<scalar_t>(),
        depth.data_ptr<scalar_t>(), t_final.data_ptr<scalar_t>(), last.data_ptr<int32_t>(),
        kept_rows.data_ptr<int16_t>(), counts);
  });
  return {rgb, alpha, depth, t_final, last, kept_rows};
}

std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor> rasterize_forward(
    const at::Tensor& means2d, const at::Tensor& conics, const at::Tensor& opacities, const at::Tensor& colors,
    const at::Tensor& depths, const at::Tensor& background, const at::Tensor& box, const at::Tensor& order,
    const at::Tensor& ids, const at::Tensor& tile_offsets, int64_t width, int64_t height, int64_t tile_size,
    int64_t threads) {
  set_threads(threads);
  return forward_pass<false>(RasterInputs(means2d, conics, opacities, colors, depths, background, box, order, ids,
                                          tile_offsets, width, height, tile_size),
                             nullptr);
}

// (alpha evaluations, contributing pairs) of the forward pass, summed over tiles.
std::tuple<int64_t, int64_t> rasterize_counts(
    const at::Tensor& means2d, const at::Tensor& conics, const at::Tensor& opacities, const at::Tensor& colors,
    const at::Tensor& depths, const at::Tensor& background, const at::Tensor& box, const at::Tensor& order,
    const at::Tensor& ids, const at::Tensor& tile_offsets, int64_t width, int64_t height, int64_t tile_size,
    int64_t threads) {
  set_threads(threads);
  const RasterInputs in(means2d, conics, opacities, colors, depths, background, box, order, ids, tile_offsets, width,
                        height, tile_size);
  std::vector<Counts> counts(in.grid.num_tiles());
  forward_pass<true>(in, &counts);
  Counts total;
  for (const Counts& c : counts) {
    total.evaluations += c.evaluations;
    total.contributions += c.contributions;
  }
  return {total.evaluations, total.contributions};
}

std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor> rasterize_backward(
    const at::Tensor& means2d, const at::Tensor& conics, const at::Tensor& opacities, const at::Tensor& colors,
    const at::Tensor& depths, const at::Tensor& background, const at::Tensor& box, const at::Tensor& order,
    const at::Tensor& ids, const at::Tensor& tile_offsets, const at::Tensor& slots, const at::Tensor& gauss_offsets,
    const at::Tensor& kept_rows, const at::Tensor& alpha, const at::Tensor& t_final, const at::Tensor& last,
    const at::Tensor& g_rgb,
    const at::Tensor& g_alpha, const at::Tensor& g_depth, int64_t width, int64_t height, int64_t tile_size,
    int64_t threads) {
  set_threads(threads);
  const RasterInputs in(means2d, conics, opacities, colors, depths, background, box, order, ids, tile_offsets, width,
                        height, tile_size);
  const int64_t n = in.means2d.size(0), pairs = in.ids.size(0);
  const auto opts = in.means2d.options();
  at::Tensor g_means2d = at::empty({n, 2}, opts), g_conics = at::empty({n, 3}, opts);
  at::Tensor g_opacities = at::empty({n}, opts), g_colors = at::empty({n, 3}, opts), g_depths = at::empty({n}, opts);
  at::Tensor g_background = at::empty({3}, opts);
  const at::Tensor sl = slots.contiguous(), go = gauss_offsets.contiguous(), a = alpha.contiguous();
  const at::Tensor kr = kept_rows.contiguous();
  TORCH_CHECK(kr.scalar_type() == at::kShort && kr.numel() == pairs, "kept_rows must be the forward's (P,) int16");
  const at::Tensor tf = t_final.contiguous(), la = last.contiguous();
  const at::Tensor gr = g_rgb.contiguous(), ga = g_alpha.contiguous(), gd = g_depth.contiguous();
  dispatch(in.means2d.scalar_type(), in.grid.tile_size, [&](auto tag, auto tile) {
    using scalar_t = decltype(tag);
    scalar_t* pair_grad = reusable_buffer<scalar_t, Buffer::kPairGrad>(static_cast<size_t>(pairs) * kPairGrad);
    std::vector<double> tile_bg(3 * static_cast<size_t>(in.grid.num_tiles()));
    raster_backward_impl<scalar_t, decltype(tile)::value>(
        in.grid, in.splats<scalar_t>(), in.ids.const_data_ptr<int32_t>(), sl.const_data_ptr<int32_t>(),
        kr.const_data_ptr<int16_t>(), in.tile_offsets.const_data_ptr<int64_t>(),
        in.background.const_data_ptr<scalar_t>(),
        a.const_data_ptr<scalar_t>(), tf.const_data_ptr<scalar_t>(), la.const_data_ptr<int32_t>(),
        gr.const_data_ptr<scalar_t>(), ga.const_data_ptr<scalar_t>(), gd.const_data_ptr<scalar_t>(),
        pair_grad, tile_bg.data());
    // Each Gaussian sums its slots in tile order.
    const int64_t* off = go.const_data_ptr<int64_t>();
    scalar_t* outs[5] = {g_means2d.data_ptr<scalar_t>(), g_conics.data_ptr<scalar_t>(),
                         g_opacities.data_ptr<scalar_t>(), g_colors.data_ptr<scalar_t>(),
                         g_depths.data_ptr<scalar_t>()};
    constexpr int widths[5] = {2, 3, 1, 3, 1};
#pragma omp parallel for schedule(static)
    for (int64_t i = 0; i < n; ++i) {
      double sum[kPairGrad] = {};
      for (int64_t j = off[i]; j < off[i + 1]; ++j) {
        for (int k = 0; k < kPairGrad; ++k) sum[k] += pair_grad[kPairGrad * j + k];
      }
      int col = 0;
      for (int o = 0; o < 5; ++o) {
        for (int k = 0; k < widths[o]; ++k) outs[o][widths[o] * i + k] = static_cast<scalar_t>(sum[col++]);
      }
    }
    scalar_t* gb = g_background.data_ptr<scalar_t>();
    for (int ch = 0; ch < 3; ++ch) {
      double sum = 0.0;
      for (int t = 0; t < in.grid.num_tiles(); ++t) sum += tile_bg[3 * t + ch];
      gb[ch] = static_cast<scalar_t>(sum);
    }
  });
  return {g_means2d, g_conics, g_opacities, g_colors, g_depths, g_background};
}

}  // namespace

TORCH_LIBRARY(interactavatar_gs, m) {
  m.def("project_forward(Tensor means, Tensor quats, Tensor scales, Tensor opacities, Tensor K, Tensor view, "
        "int width, int height, float near, float far, int threads) -> (Tensor, Tensor, Tensor, Tensor, Tensor, Tensor)",
        &project_forward);
  m.def("project_backward(Tensor means, Tensor quats, Tensor scales, Tensor K, Tensor view, int width, int height, "
        "float near, float far, Tensor g_means2d, Tensor g_conics, Tensor g_depths, int threads) "
        "-> (Tensor, Tensor, Tensor)",
        &project_backward);
  m.def("bin_tiles(Tensor box, Tensor depths, Tensor visible, int width, int height, int tile_size, int threads) "
        "-> (Tensor, Tensor, Tensor, Tensor, Tensor)",
        &bin_tiles);
  m.def("rasterize_forward(Tensor means2d, Tensor conics, Tensor opacities, Tensor colors, Tensor depths, "
        "Tensor background, Tensor box, Tensor order, Tensor ids, Tensor tile_offsets, int width, int height, "
        "int tile_size, int threads) -> (Tensor, Tensor, Tensor, Tensor, Tensor, Tensor)",
        &rasterize_forward);
  m.def("rasterize_counts(Tensor means2d, Tensor conics, Tensor opacities, Tensor colors, Tensor depths, "
        "Tensor background, Tensor box, Tensor order, Tensor ids, Tensor tile_offsets, int width, int height, "
        "int tile_size, int threads) -> (int, int)",
        &rasterize_counts);
  m.def("rasterize_backward(Tensor means2d, Tensor conics, Tensor opacities, Tensor colors, Tensor depths, "
        "Tensor background, Tensor box, Tensor order, Tensor ids, Tensor tile_offsets, Tensor slots, "
        "Tensor gauss_offsets, Tensor kept_rows, Tensor alpha, Tensor t_final, Tensor last, Tensor g_rgb, "
        "Tensor g_alpha, "
        "Tensor g_depth, int width, int height, int tile_size, int threads) "
        "-> (Tensor, Tensor, Tensor, Tensor, Tensor, Tensor)",
        &rasterize_backward);
}
