// A MATLAB v7.3 file (HDF5 behind its 128-byte header) whose one variable P1b claims 32768 x 4096
// doubles (1 GiB) in 1,912 bytes: a chunked, deflated dataset none of whose chunks is stored, which
// HDF5 reads as its fill value. Wrote tests/data/hostile/v73_claims_1gb.mat (issue 113):
//   cc make_v73_claim.c -o make_v73_claim $(pkg-config --cflags --libs hdf5) && ./make_v73_claim OUT.mat
#include <hdf5.h>
#include <string.h>
#include <stdio.h>
int main(int argc, char** argv) {
  hid_t fcpl = H5Pcreate(H5P_FILE_CREATE);
  H5Pset_userblock(fcpl, 512);
  hid_t f = H5Fcreate(argv[1], H5F_ACC_TRUNC, fcpl, H5P_DEFAULT);
  hsize_t dims[2] = {4096, 32768};  // MATLAB's 32768 x 4096, column-major
  hid_t space = H5Screate_simple(2, dims, NULL);
  hid_t dcpl = H5Pcreate(H5P_DATASET_CREATE);
  hsize_t chunk[2] = {64, 64};
  H5Pset_chunk(dcpl, 2, chunk);
  H5Pset_deflate(dcpl, 9);
  hid_t d = H5Dcreate2(f, "P1b", H5T_NATIVE_DOUBLE, space, H5P_DEFAULT, dcpl, H5P_DEFAULT);
  hid_t str = H5Tcopy(H5T_C_S1);
  H5Tset_size(str, 6);
  hid_t as = H5Screate(H5S_SCALAR);
  hid_t a = H5Acreate2(d, "MATLAB_class", str, as, H5P_DEFAULT, H5P_DEFAULT);
  H5Awrite(a, str, "double");
  H5Aclose(a); H5Sclose(as); H5Tclose(str);
  H5Dclose(d); H5Pclose(dcpl); H5Sclose(space); H5Fclose(f); H5Pclose(fcpl);
  // MATLAB's 128-byte v7.3 header in the user block.
  FILE* fp = fopen(argv[1], "r+b");
  char head[128];
  memset(head, ' ', 116);
  memcpy(head, "MATLAB 7.3 MAT-file, hostile claim", 34);
  memset(head + 116, 0, 8);
  head[124] = 0x00; head[125] = 0x02; head[126] = 'I'; head[127] = 'M';
  fwrite(head, 1, 128, fp);
  fclose(fp);
  return 0;
}
