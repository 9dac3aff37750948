// A v7.3 (HDF5) calibration for fuzz_calibration's tiny camera (12x14 planes, 8-pixel scenes), as
// matio writes it (MATLAB's -v7.3 layout): P1b..P1r {12,8} and Q1b..Q1r {14,8}, zlib-compressed.
// Built and run by tests/fuzz/make_seeds.sh: make_v73_seed OUT.mat
#include <matio.h>
#include <stdio.h>
#include <stdlib.h>

static void put(mat_t* mat, const char* name, size_t rows, size_t cols, double base) {
  size_t dims[2] = {rows, cols};
  double* data = malloc(sizeof(double) * rows * cols);
  for (size_t i = 0; i < rows * cols; ++i) data[i] = base + 0.001 * (double)(i % 7);
  matvar_t* v = Mat_VarCreate(name, MAT_C_DOUBLE, MAT_T_DOUBLE, 2, dims, data, 0);
  Mat_VarWrite(mat, v, MAT_COMPRESSION_ZLIB);
  Mat_VarFree(v);
  free(data);
}

int main(int argc, char** argv) {
  if (argc != 2) return 2;
  mat_t* mat = Mat_CreateVer(argv[1], NULL, MAT_FT_MAT73);
  if (!mat) return 1;
  const char* channels[4] = {"b", "gb", "gr", "r"};
  char name[8];
  for (int c = 0; c < 4; ++c) {
    snprintf(name, sizeof name, "P1%s", channels[c]);
    put(mat, name, 12, 8, 0.002 * (c + 1));
    snprintf(name, sizeof name, "Q1%s", channels[c]);
    put(mat, name, 14, 8, 0.003 * (c + 1));
  }
  Mat_Close(mat);
  return 0;
}
