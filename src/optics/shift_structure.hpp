#pragma once
// The shift structure of a FlatCam factor (P or Q of Y = P X Q^T), used to identify a calibration
// from few, noisy display captures (optics/calibrate_dataset.hpp).
//
// One step along a scene axis moves the mask's shadow by a fixed distance on the sensor, so column j
// of a factor is column 0 moved by j * shift sensor pixels (camera README, "Building this camera":
// the shadow of scene column j sits at t + (N - 1 - j) + offset mask features):
//   F[i,j] = f(i + j * shift),                                                             (1)
// one profile f (the mask's code seen through the pixels' area and the optics' blur) sampled every
// `spacing` sensor pixels and interpolated linearly. (1) has about m + N |shift| unknowns where the
// free factor has m N: about 1,000 against 128,000 for FlatNet's 500 x 256 P, which is what lets a few
// hundred noisy photographs identify it. What (1) leaves out (vignetting, edge effects of the blur)
// is a few per cent of the factor: 5.5 % on the reference camera's P with spacing 1.
//
// The fit: given one alternating step's normal equations (G = sum Z Z^T {N,N}, H = sum Y Z^T {m,N}
// per channel, the uniform-light term already eliminated), minimise
//   J(f) = tr(C F G F^T) - 2 <F, H>,     F = F(f),  C = I - 1 1^T / m (captures are centred),  (2)
// by conjugate gradients on f. The least J over f is a smooth, single-welled function of the shift
// around the true one, so the shift is found on a coarse geometric grid over both signs, then by
// golden-section search.
#include <functional>

#include <torch/torch.h>

namespace flatnet {

// The search's bounds: a shadow that moves less than a twentieth of a sensor pixel per scene pixel
// is not a FlatCam's (a 256-pixel scene would move it by under 13 pixels), and a grid finer than 1 %
// only costs time. With these the coarse grid is at most log(16/0.05)/log(1.01) ~ 580 points a sign.
constexpr double kSmallestShiftSearched = 0.05, kLargestShiftSearched = 16.0, kFinestShiftGridStep = 0.01;

struct ShiftFitOptions {
  double spacing = 1.0;    // sensor pixels between the profile's samples
  double min_shift = 0.5;  // |shift| searched, sensor pixels per scene pixel
  double max_shift = 8.0;
  double grid_step = 0.1;         // the coarse grid's relative step
  double shift_tolerance = 2e-4;  // golden-section search ends at this relative bracket
  int search_iterations = 100;    // conjugate-gradient steps per trial shift on the coarse grid
  int fit_iterations = 400;       // ... in the golden-section search and the final fit
  double cg_tolerance = 1e-7;     // ... or until the residual falls below this, relative
};

struct ShiftFactor {
  double shift = 0;         // sensor pixels per scene pixel, signed
  torch::Tensor profile;    // {C,L} f per channel, float64
  torch::Tensor factor;     // {C,m,N} the centred factor C F(f), float64
  torch::Tensor objective;  // {C} J at the fit, float64
};

// The samples a profile needs for a factor of `rows` sensor rows and `scene` scene pixels at `shift`.
int64_t shift_profile_length(int64_t rows, int64_t scene, double shift, double spacing);
// The centred factor C F(f) of (1) for a profile {C,L}.
torch::Tensor shift_factor(const torch::Tensor& profile, int64_t rows, int64_t scene, double shift, double spacing);

// The least-squares profile (2) for one shift. G {C,N,N}, H {C,m,N}; `warm` a profile {C,L} to start from.
ShiftFactor fit_shift_factor(const torch::Tensor& G, const torch::Tensor& H, double shift, const ShiftFitOptions& o,
                             int max_iterations, const torch::Tensor& warm = {});

// The same least-squares profile solved exactly (spacing 1): J's normal matrix built from the
// structure and factored, instead of conjugate gradients. With spacing 1 the interpolation weight of
// column j does not depend on the row (F[i,j] = (1 - w_j) f[i + d_j] + w_j f[i + d_j + 1]), so
//   sum_i F[i,:] G F[i,:]^T = f^T A f,   A[k,l] = sum_{i<m} M0[k - i, l - i],   M0 = T0^T G T0,
// where T0 {N,W} maps f to row 0: A is M0 summed along its diagonals over a window of m rows. The
// centring subtracts (1/m) S^T G S, S = sum_i T_i {N,L}. One solve per shift (about 0.1 s for the
// FlatNet prototype's 742 samples, against ~40 s for 400 CG steps): what makes a full shift search
// over both axes affordable when each evaluation must be converged.
ShiftFactor solve_shift_factor(const torch::Tensor& G, const torch::Tensor& H, double shift);

// The normal equations solve_shift_factor solves, A f = rhs per channel (A {C,L,L} with the ridge,
// rhs {C,L}): for fits that tie the channels' profiles together.
struct ShiftNormalEquations {
  torch::Tensor A, rhs;
};
ShiftNormalEquations shift_normal_equations(const torch::Tensor& G, const torch::Tensor& H, double shift);

// One mask for every channel. The four Bayer planes sit behind one mask: each sees its shadow from
// half a pixel away, through its own colour's diffraction, at its own gain. So each channel's profile
// is one mask profile m convolved with a short kernel of its own (a sub-pixel offset, a blur and a
// gain in one linear filter, `taps` samples wide):
//   f_c[t] = sum_tau k_c[tau] m[t - tau],   tau = -h..h,                                  (3)
// and J of (2) summed over the channels is minimised by alternation: m for fixed kernels (one L x L
// solve of sum_c K_c^T A_c K_c), then each kernel for fixed m (a taps x taps solve). The scale is split
// by holding the kernels' mean |sum| at 1; each kernel's taps are held to one sign (a blur moved by a
// sub-pixel offset spreads light, it never subtracts it), which keeps a kernel from fitting noise. A channel then
// cannot fit its own noise as a profile of its own: the planes' profiles agree up to their kernels by construction.
struct SharedShiftFactor {
  ShiftFactor fit;        // the channels' profiles f_c of (3) and their factors
  torch::Tensor mask;     // {L} m
  torch::Tensor kernels;  // {C,taps} k_c
};
// kernels {C,taps} (odd) start the alternation (a unit impulse at the centre for a first fit).
SharedShiftFactor solve_shared_shift_factor(const torch::Tensor& G, const torch::Tensor& H, double shift,
                                            const torch::Tensor& kernels, int alternations);

// Golden-section search for the least f on [lo, hi] (a single well inside), to a relative bracket
// `tolerance`; the shift searches' last stage.
double golden_section_minimum(const std::function<double(double)>& f, double lo, double hi, double tolerance);

// The shift of least J + 2 sigma2 L, summed over the channels of G and H: the coarse grid over both
// signs, then golden-section search between the best point's neighbours. Larger shifts mean longer profiles (L
// samples), and each sample fitted to noise alone lowers J by sigma2, the noise's variance per capture value: Akaike's
// penalty 2 sigma2 L keeps noisy pairs from choosing the most flexible structure. sigma2 = 0 compares J alone.
double search_shift(const torch::Tensor& G, const torch::Tensor& H, const ShiftFitOptions& o, double sigma2 = 0);

}  // namespace flatnet
