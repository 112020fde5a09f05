// The CPU rasteriser's conventions, those of the torch backend (plugins/mappers/gaussian_splatting/rasterizer/torch_rasterizer.py;
// cpu_rasterizer.cpp's first comment lists them): tile size and the constants of the projection and
// the compositing.
#pragma once

namespace {

constexpr int TILE = 16;
constexpr double NEAR_PLANE = 0.01;
constexpr double EPS_2D = 0.3;
constexpr float ALPHA_MAX = 0.99f;
constexpr double T_MIN = 1e-4;
constexpr double JACOBIAN_MARGIN = 0.15;

}  // namespace
