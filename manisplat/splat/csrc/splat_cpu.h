// Entry points of the CPU splatting extension (bound in rasterize_cpu.cpp).
#pragma once

#include <torch/extension.h>

#include <vector>

// Projection of N Gaussians into one camera: means2d [N, 2], conics [N, 3], depths [N], radii [N, 2].
std::vector<torch::Tensor> project_forward(torch::Tensor means, torch::Tensor quats, torch::Tensor scales,
                                           torch::Tensor opacities, torch::Tensor viewmat, torch::Tensor K,
                                           int64_t width, int64_t height, double near, double far, double eps2d);

// Gradients w.r.t. means [N, 3], quats [N, 4], scales [N, 3] and the viewmat [4, 4].
std::vector<torch::Tensor> project_backward(torch::Tensor means, torch::Tensor quats, torch::Tensor scales,
                                            torch::Tensor viewmat, torch::Tensor K, int64_t width, int64_t height,
                                            double eps2d, torch::Tensor radii, torch::Tensor g_means2d,
                                            torch::Tensor g_conics, torch::Tensor g_depths);
