// EWA projection of 3D Gaussians into one pinhole camera, forward and analytic backward.
//
// Same arithmetic as manisplat/splat/projection.py (the autograd oracle), in double precision
// whatever the tensor dtype: quaternion (normalised, norm floored at 1e-12) and scales give
// Sigma = R S S^T R^T; the camera-space mean t = W mu + T; the Jacobian of the pinhole with
// x/z, y/z clamped to the principal-point-aware frustum box; Sigma2D = J W Sigma W^T J^T + eps2d I;
// conic = inverse(Sigma2D); per-axis radii from the opacity-aware 3.33-sigma extent. Culled
// Gaussians (outside [near, far], det <= 0, opacity < 1/255, box off the image) get radius 0
// and no gradient.

#include "splat_cpu.h"

#include <ATen/Parallel.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <vector>

namespace {

using Mat3 = std::array<std::array<double, 3>, 3>;
using Vec3 = std::array<double, 3>;

constexpr double kAlphaThreshold = 1.0 / 255.0;
constexpr double kMaxExtent = 3.33;
constexpr double kQuatFloor = 1e-12;

Mat3 quat_to_rot(const double* q) {
  const double w = q[0], x = q[1], y = q[2], z = q[3];
  return {{{1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)},
           {2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)},
           {2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)}}};
}

// Gradient of the quaternion given dL/dR for R = quat_to_rot(q).
std::array<double, 4> quat_to_rot_vjp(const double* q, const Mat3& G) {
  const double w = q[0], x = q[1], y = q[2], z = q[3];
  std::array<double, 4> g{};
  g[0] = 2 * (x * (G[2][1] - G[1][2]) + y * (G[0][2] - G[2][0]) + z * (G[1][0] - G[0][1]));
  g[1] = 2 * (-2 * x * (G[1][1] + G[2][2]) + y * (G[1][0] + G[0][1]) + z * (G[2][0] + G[0][2]) +
              w * (G[2][1] - G[1][2]));
  g[2] = 2 * (x * (G[1][0] + G[0][1]) - 2 * y * (G[0][0] + G[2][2]) + z * (G[2][1] + G[1][2]) +
              w * (G[0][2] - G[2][0]));
  g[3] = 2 * (x * (G[2][0] + G[0][2]) + y * (G[2][1] + G[1][2]) - 2 * z * (G[0][0] + G[1][1]) +
              w * (G[1][0] - G[0][1]));
  return g;
}

struct Camera {
  Mat3 W;
  Vec3 T;
  double fx, fy, cx, cy;
  double lim_x_pos, lim_x_neg, lim_y_pos, lim_y_neg;
};

template <typename T>
Camera read_camera(const T* viewmat, const T* K, int64_t width, int64_t height) {
  Camera cam;
  for (int i = 0; i < 3; ++i) {
    for (int j = 0; j < 3; ++j) cam.W[i][j] = viewmat[4 * i + j];
    cam.T[i] = viewmat[4 * i + 3];
  }
  cam.fx = K[0];
  cam.fy = K[4];
  cam.cx = K[2];
  cam.cy = K[5];
  const double tan_x = 0.5 * width / cam.fx, tan_y = 0.5 * height / cam.fy;
  cam.lim_x_pos = (width - cam.cx) / cam.fx + 0.3 * tan_x;
  cam.lim_x_neg = cam.cx / cam.fx + 0.3 * tan_x;
  cam.lim_y_pos = (height - cam.cy) / cam.fy + 0.3 * tan_y;
  cam.lim_y_neg = cam.cy / cam.fy + 0.3 * tan_y;
  return cam;
}

// Everything the forward computes for one Gaussian that the backward needs again.
struct Forward {
  double qn[4], qnorm;
  Mat3 R, M, Sigma, Sc;  // rotation, R S, world covariance, camera covariance
  Vec3 mc;
  double xr, yr;         // clamped x/z, y/z
  bool x_free, y_free;   // not clamped
  double J[2][3];
  double a, b, c, det;   // Sigma2D (with eps2d) entries
  bool in_depth;
};

template <typename T>
Forward forward_one(const T* mean, const T* quat, const T* scale, const Camera& cam, double eps2d) {
  Forward f;
  const double q[4] = {quat[0], quat[1], quat[2], quat[3]};
  f.qnorm = std::max(std::sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]), kQuatFloor);
  for (int i = 0; i < 4; ++i) f.qn[i] = q[i] / f.qnorm;
  f.R = quat_to_rot(f.qn);
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) f.M[i][j] = f.R[i][j] * static_cast<double>(scale[j]);
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j)
      f.Sigma[i][j] = f.M[i][0] * f.M[j][0] + f.M[i][1] * f.M[j][1] + f.M[i][2] * f.M[j][2];
  for (int i = 0; i < 3; ++i)
    f.mc[i] = cam.W[i][0] * mean[0] + cam.W[i][1] * mean[1] + cam.W[i][2] * mean[2] + cam.T[i];
  Mat3 WS{};
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j)
      for (int k = 0; k < 3; ++k) WS[i][j] += cam.W[i][k] * f.Sigma[k][j];
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) {
      f.Sc[i][j] = 0;
      for (int k = 0; k < 3; ++k) f.Sc[i][j] += WS[i][k] * cam.W[j][k];
    }
  const double tz = f.mc[2];
  const double x = f.mc[0] / tz, y = f.mc[1] / tz;
  f.xr = std::min(std::max(x, -cam.lim_x_neg), cam.lim_x_pos);
  f.yr = std::min(std::max(y, -cam.lim_y_neg), cam.lim_y_pos);
  f.x_free = x >= -cam.lim_x_neg && x <= cam.lim_x_pos;
  f.y_free = y >= -cam.lim_y_neg && y <= cam.lim_y_pos;
  f.J[0][0] = cam.fx / tz; f.J[0][1] = 0; f.J[0][2] = -cam.fx * f.xr / tz;
  f.J[1][0] = 0; f.J[1][1] = cam.fy / tz; f.J[1][2] = -cam.fy * f.yr / tz;
  double JS[2][3] = {};
  for (int i = 0; i < 2; ++i)
    for (int j = 0; j < 3; ++j)
      for (int k = 0; k < 3; ++k) JS[i][j] += f.J[i][k] * f.Sc[k][j];
  double S2[2][2] = {};
  for (int i = 0; i < 2; ++i)
    for (int j = 0; j < 2; ++j)
      for (int k = 0; k < 3; ++k) S2[i][j] += JS[i][k] * f.J[j][k];
  f.a = S2[0][0] + eps2d;
  f.b = S2[0][1];
  f.c = S2[1][1] + eps2d;
  f.det = f.a * f.c - f.b * f.b;
  return f;
}

template <typename T>
void project_impl(const T* means, const T* quats, const T* scales, const T* opacities, const T* viewmat, const T* K,
                  int64_t N, int64_t width, int64_t height, double near, double far, double eps2d, T* means2d,
                  T* conics, T* depths, int32_t* radii) {
  const Camera cam = read_camera(viewmat, K, width, height);
  at::parallel_for(0, N, 1024, [&](int64_t begin, int64_t end) {
    for (int64_t g = begin; g < end; ++g) {
      const Forward f = forward_one(means + 3 * g, quats + 4 * g, scales + 3 * g, cam, eps2d);
      const double tz = f.mc[2];
      const bool in_depth = tz >= near && tz <= far;
      const double tz_safe = in_depth ? tz : 1.0;
      const double u = cam.fx * f.mc[0] / tz_safe + cam.cx, v = cam.fy * f.mc[1] / tz_safe + cam.cy;
      const bool ok_det = in_depth && f.det > 0;
      const double o = opacities[g];
      const bool ok_opacity = o >= kAlphaThreshold;
      const double extent = std::min(kMaxExtent, std::sqrt(2.0 * std::log((ok_opacity ? o : 1.0) / kAlphaThreshold)));
      const double rx = std::ceil(extent * std::sqrt(std::max(f.a, 0.0)));
      const double ry = std::ceil(extent * std::sqrt(std::max(f.c, 0.0)));
      const bool on_image = u + rx > 0 && u - rx < width && v + ry > 0 && v - ry < height;
      const bool keep = ok_det && ok_opacity && on_image && rx > 0 && ry > 0 && std::isfinite(rx) && std::isfinite(ry);
      const double det = ok_det ? f.det : 1.0;
      means2d[2 * g] = static_cast<T>(u);
      means2d[2 * g + 1] = static_cast<T>(v);
      conics[3 * g] = static_cast<T>(f.c / det);
      conics[3 * g + 1] = static_cast<T>(-f.b / det);
      conics[3 * g + 2] = static_cast<T>(f.a / det);
      depths[g] = static_cast<T>(tz);
      radii[2 * g] = keep ? static_cast<int32_t>(std::min(rx, 1073741824.0)) : 0;
      radii[2 * g + 1] = keep ? static_cast<int32_t>(std::min(ry, 1073741824.0)) : 0;
    }
  });
}

template <typename T>
void project_backward_impl(const T* means, const T* quats, const T* scales, const T* viewmat, const T* K, int64_t N,
                           int64_t width, int64_t height, double eps2d, const int32_t* radii, const T* g_means2d,
                           const T* g_conics, const T* g_depths, T* g_means, T* g_quats, T* g_scales,
                           std::array<double, 12>& g_view) {
  const Camera cam = read_camera(viewmat, K, width, height);
  const int64_t workers = std::max<int64_t>(1, at::get_num_threads());
  std::vector<std::array<double, 12>> view_parts(workers, std::array<double, 12>{});  // dL/dW (9), dL/dT (3)
  at::parallel_for(0, workers, 1, [&](int64_t wb, int64_t we) {
    for (int64_t worker = wb; worker < we; ++worker) {
      const int64_t chunk = (N + workers - 1) / workers;
      std::array<double, 12> gv{};  // this worker's sum, kept local (no cache line shared with another's)
      for (int64_t g = worker * chunk; g < std::min(N, (worker + 1) * chunk); ++g) {
        for (int i = 0; i < 3; ++i) g_means[3 * g + i] = 0, g_scales[3 * g + i] = 0;
        for (int i = 0; i < 4; ++i) g_quats[4 * g + i] = 0;
        if (radii[2 * g] <= 0 || radii[2 * g + 1] <= 0) continue;  // culled: no gradient
        const T* mean = means + 3 * g;
        const Forward f = forward_one(mean, quats + 4 * g, scales + 3 * g, cam, eps2d);
        const double tz = f.mc[2], tx = f.mc[0], ty = f.mc[1];
        // conic = inverse(Sigma2D): dL/dSigma2D = -inv G inv, G the symmetric conic gradient
        const double inv[2][2] = {{f.c / f.det, -f.b / f.det}, {-f.b / f.det, f.a / f.det}};
        const double gC[2][2] = {{static_cast<double>(g_conics[3 * g]), 0.5 * g_conics[3 * g + 1]},
                                 {0.5 * g_conics[3 * g + 1], static_cast<double>(g_conics[3 * g + 2])}};
        double tmp[2][2] = {}, gS2[2][2] = {};
        for (int i = 0; i < 2; ++i)
          for (int j = 0; j < 2; ++j)
            for (int k = 0; k < 2; ++k) tmp[i][j] += inv[i][k] * gC[k][j];
        for (int i = 0; i < 2; ++i)
          for (int j = 0; j < 2; ++j)
            for (int k = 0; k < 2; ++k) gS2[i][j] -= tmp[i][k] * inv[k][j];
        // Sigma2D = J Sc J^T: dL/dJ = 2 gS2 J Sc, dL/dSc = J^T gS2 J
        double gJ[2][3] = {}, JSc[2][3] = {};
        for (int i = 0; i < 2; ++i)
          for (int j = 0; j < 3; ++j)
            for (int k = 0; k < 3; ++k) JSc[i][j] += f.J[i][k] * f.Sc[k][j];
        for (int i = 0; i < 2; ++i)
          for (int j = 0; j < 3; ++j)
            for (int k = 0; k < 2; ++k) gJ[i][j] += 2 * gS2[i][k] * JSc[k][j];
        Mat3 gSc{};
        for (int i = 0; i < 3; ++i)
          for (int j = 0; j < 3; ++j)
            for (int k = 0; k < 2; ++k)
              for (int l = 0; l < 2; ++l) gSc[i][j] += f.J[k][i] * gS2[k][l] * f.J[l][j];
        // camera-space mean: pixel position, depth, and the Jacobian's dependence on t
        double gt[3] = {0, 0, static_cast<double>(g_depths[g])};
        const double gu = g_means2d[2 * g], gv2 = g_means2d[2 * g + 1];
        gt[0] += gu * cam.fx / tz;
        gt[1] += gv2 * cam.fy / tz;
        gt[2] += -gu * cam.fx * tx / (tz * tz) - gv2 * cam.fy * ty / (tz * tz);
        gt[2] += -gJ[0][0] * cam.fx / (tz * tz) - gJ[1][1] * cam.fy / (tz * tz);
        // J02 = -fx xr / tz with xr = clamp(tx / tz): free -> depends on tx and tz, clamped -> tz only
        gt[2] += gJ[0][2] * cam.fx * f.xr / (tz * tz) + gJ[1][2] * cam.fy * f.yr / (tz * tz);
        if (f.x_free) {
          gt[0] += -gJ[0][2] * cam.fx / (tz * tz);
          gt[2] += gJ[0][2] * cam.fx * tx / (tz * tz * tz);
        }
        if (f.y_free) {
          gt[1] += -gJ[1][2] * cam.fy / (tz * tz);
          gt[2] += gJ[1][2] * cam.fy * ty / (tz * tz * tz);
        }
        // t = W mu + T
        for (int j = 0; j < 3; ++j)
          g_means[3 * g + j] = static_cast<T>(cam.W[0][j] * gt[0] + cam.W[1][j] * gt[1] + cam.W[2][j] * gt[2]);
        for (int i = 0; i < 3; ++i) {
          for (int j = 0; j < 3; ++j) gv[3 * i + j] += gt[i] * static_cast<double>(mean[j]);
          gv[9 + i] += gt[i];
        }
        // Sc = W Sigma W^T: dL/dSigma = W^T gSc W, dL/dW += 2 gSc W Sigma (gSc, Sigma symmetric)
        Mat3 gSigma{}, WSig{};
        for (int i = 0; i < 3; ++i)
          for (int j = 0; j < 3; ++j)
            for (int k = 0; k < 3; ++k) WSig[i][j] += cam.W[i][k] * f.Sigma[k][j];
        for (int i = 0; i < 3; ++i)
          for (int j = 0; j < 3; ++j) {
            double acc = 0;
            for (int k = 0; k < 3; ++k)
              for (int l = 0; l < 3; ++l) acc += cam.W[k][i] * gSc[k][l] * cam.W[l][j];
            gSigma[i][j] = acc;
            double gw = 0;
            for (int k = 0; k < 3; ++k) gw += 2 * gSc[i][k] * WSig[k][j];
            gv[3 * i + j] += gw;
          }
        // Sigma = M M^T with M = R diag(s): dL/dM = 2 gSigma M
        Mat3 gR{};
        for (int i = 0; i < 3; ++i)
          for (int j = 0; j < 3; ++j) {
            double gM = 0;
            for (int k = 0; k < 3; ++k) gM += 2 * gSigma[i][k] * f.M[k][j];
            gR[i][j] = gM * static_cast<double>(scales[3 * g + j]);
            g_scales[3 * g + j] += static_cast<T>(gM * f.R[i][j]);
          }
        // R = rot(q / |q|)
        const std::array<double, 4> gqn = quat_to_rot_vjp(f.qn, gR);
        const double dot = gqn[0] * f.qn[0] + gqn[1] * f.qn[1] + gqn[2] * f.qn[2] + gqn[3] * f.qn[3];
        const bool floored = f.qnorm <= kQuatFloor;
        for (int i = 0; i < 4; ++i)
          g_quats[4 * g + i] = static_cast<T>((floored ? gqn[i] : gqn[i] - f.qn[i] * dot) / f.qnorm);
      }
      view_parts[worker] = gv;
    }
  });
  for (const auto& part : view_parts)
    for (int i = 0; i < 12; ++i) g_view[i] += part[i];  // [dL/dW row-major (9), dL/dT (3)]
}

}  // namespace

std::vector<torch::Tensor> project_forward(torch::Tensor means, torch::Tensor quats, torch::Tensor scales,
                                           torch::Tensor opacities, torch::Tensor viewmat, torch::Tensor K,
                                           int64_t width, int64_t height, double near, double far, double eps2d) {
  const int64_t N = means.size(0);
  auto opts = means.options();
  auto means2d = torch::empty({N, 2}, opts), conics = torch::empty({N, 3}, opts), depths = torch::empty({N}, opts);
  auto radii = torch::empty({N, 2}, opts.dtype(torch::kInt32));
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "manisplat_project_forward", [&] {
    project_impl<scalar_t>(means.data_ptr<scalar_t>(), quats.data_ptr<scalar_t>(), scales.data_ptr<scalar_t>(),
                           opacities.data_ptr<scalar_t>(), viewmat.data_ptr<scalar_t>(), K.data_ptr<scalar_t>(), N,
                           width, height, near, far, eps2d, means2d.data_ptr<scalar_t>(), conics.data_ptr<scalar_t>(),
                           depths.data_ptr<scalar_t>(), radii.data_ptr<int32_t>());
  });
  return {means2d, conics, depths, radii};
}

std::vector<torch::Tensor> project_backward(torch::Tensor means, torch::Tensor quats, torch::Tensor scales,
                                            torch::Tensor viewmat, torch::Tensor K, int64_t width, int64_t height,
                                            double eps2d, torch::Tensor radii, torch::Tensor g_means2d,
                                            torch::Tensor g_conics, torch::Tensor g_depths) {
  const int64_t N = means.size(0);
  auto g_means = torch::empty_like(means), g_quats = torch::empty_like(quats), g_scales = torch::empty_like(scales);
  std::array<double, 12> g_view{};
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "manisplat_project_backward", [&] {
    project_backward_impl<scalar_t>(means.data_ptr<scalar_t>(), quats.data_ptr<scalar_t>(),
                                    scales.data_ptr<scalar_t>(), viewmat.data_ptr<scalar_t>(), K.data_ptr<scalar_t>(),
                                    N, width, height, eps2d, radii.data_ptr<int32_t>(),
                                    g_means2d.data_ptr<scalar_t>(), g_conics.data_ptr<scalar_t>(),
                                    g_depths.data_ptr<scalar_t>(), g_means.data_ptr<scalar_t>(),
                                    g_quats.data_ptr<scalar_t>(), g_scales.data_ptr<scalar_t>(), g_view);
  });
  auto g_viewmat = torch::zeros({4, 4}, torch::kFloat64);
  auto acc = g_viewmat.accessor<double, 2>();
  for (int i = 0; i < 3; ++i) {
    for (int j = 0; j < 3; ++j) acc[i][j] = g_view[3 * i + j];
    acc[i][3] = g_view[9 + i];
  }
  return {g_means, g_quats, g_scales, g_viewmat.to(means.scalar_type())};
}
