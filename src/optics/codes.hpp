#pragma once
// Mask codes and the separable FlatCam matrices they give.
#include <filesystem>
#include <string>
#include <vector>

#include <torch/torch.h>

namespace flatnet {

// Maximum-length sequence of length 2^n - 1 (n = 2..24) from a Fibonacci LFSR with a primitive
// feedback polynomial; values +1/-1 (bit 1 -> +1). Its cyclic autocorrelation is N at lag 0 and -1
// elsewhere, which makes the FlatCam matrices well conditioned.
std::vector<int> mls(int n);

// FlatNet's 31-element "02" pattern 1110001011100100001111111111111 (values 0/1).
std::vector<int> flatnet_m02_pattern();

// Sylvester Hadamard matrix, n a power of two, entries +-1. {n,n} float64.
torch::Tensor hadamard(int64_t n);

// Geometry of a separable amplitude mask over a sensor (one axis).
struct MaskGeometry {
  double feature_um = 20.0;               // mask feature (code element) size
  double pixel_pitch_um = 10.6;           // sensor pixel pitch (of one Bayer plane)
  double shift_features_per_pixel = 1.0;  // shadow shift per scene pixel, in mask features
  double blur_px = 0.0;                   // Gaussian blur sigma, sensor pixels (diffraction)
  int64_t sensor_pixels = 500;            // rows (PhiL) or columns (PhiR)
  int64_t scene_pixels = 256;
};

// Separable FlatCam matrix Phi {sensor_pixels, scene_pixels} for a 0/1 (or +-1) code: entry (i, j)
// is the code's transmittance averaged over sensor pixel i when the shadow is shifted for scene
// pixel j (the code is centred on the sensor for the middle scene pixel), then blurred.
torch::Tensor toeplitz_phi(const std::vector<int>& code, const MaskGeometry& g);
torch::Tensor toeplitz_phi(const std::vector<double>& code, const MaskGeometry& g);  // graded transmittance

// FlatNet's calibration-free initialisation (thesis, sec. "calibration-free FlatNet"): a
// Toeplitz-like matrix whose column j is a random sequence shifted by j * slope sensor pixels,
// scaled to largest singular value 0.5. slope = shift_features_per_pixel * feature / pitch.
torch::Tensor calibration_free_phi(int64_t rows, int64_t cols, double slope, uint64_t seed);
double geometry_slope(const MaskGeometry& g);

// FlatNet's released phil_toep_slope22.mat / phir_toep_slope22.mat: `phil` {500,256,4},
// `phir` {620,256,4} -> {4,500,256} and {4,620,256} float64.
torch::Tensor load_flatnet_toeplitz(const std::filesystem::path& path, const std::string& variable);

}  // namespace flatnet
