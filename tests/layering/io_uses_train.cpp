// Preprocessed with io's include folders only (CMakeLists.txt, tests layers_io_*): io may not use train,
// so this include must fail with "No such file".
#include "train/experiment.hpp"
