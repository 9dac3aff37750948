// Preprocessed with io's include folders only (CMakeLists.txt, tests layers_io_*): io may use its own headers.
#include "io/config.hpp"
