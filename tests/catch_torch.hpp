#pragma once
// Catch2 after LibTorch, always: LibTorch's glog defines a CHECK macro of its own, and whichever
// header comes last owns the name. Every test includes this instead of <catch2/catch.hpp>, so the
// tests mean Catch2's CHECK with or without the precompiled header.
#include <torch/torch.h>

#include <catch2/catch.hpp>
