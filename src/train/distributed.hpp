#pragma once
// Data-parallel training over processes and machines with PyTorch's own engine, c10d: a TCPStore
// rendezvous (rank 0 hosts it at MASTER_ADDR:MASTER_PORT) and ProcessGroupGloo collectives, set up
// the way torchrun sets up a job (WORLD_SIZE, RANK, MASTER_ADDR, MASTER_PORT).
//
// With a CUDA build of LibTorch the same code would create c10d::ProcessGroupNCCL (options: the
// store, rank, size, and a CUDA stream per device) and keep gradients on the GPU; Gloo stays the
// choice for CPU tensors. Nothing else in the trainer changes.
#include <chrono>
#include <memory>
#include <string>
#include <vector>

#include <torch/torch.h>

#include "train/gan_trainer.hpp"

namespace c10d {
class ProcessGroupGloo;
class Store;
}  // namespace c10d

namespace flatnet {

struct DistributedOptions {
  int world_size = 1;
  int rank = 0;
  std::string master_addr = "127.0.0.1";
  int master_port = 29500;
  double timeout_s = 300;           // a collective that waits longer fails (a rank died or hangs)
  int64_t bucket_bytes = 25 << 20;  // gradients are all-reduced in buckets of about this size
};

// torchrun's environment: WORLD_SIZE, RANK, MASTER_ADDR, MASTER_PORT (absent: one process).
// Errors name the variable holding a bad value.
DistributedOptions distributed_from_env();

class ProcessGroup final : public GradientAverager {
 public:
  explicit ProcessGroup(const DistributedOptions& options);  // blocks until all ranks joined
  ~ProcessGroup() override;
  int rank() const override { return opt_.rank; }
  int world_size() const override { return opt_.world_size; }

  // Gradients of `params` <- their mean over all ranks (bucketed, flattened all-reduce).
  void average(const std::vector<torch::Tensor>& params) override;
  // Tensors <- rank 0's values (initial parameters, batch-norm running statistics).
  void broadcast(const std::vector<torch::Tensor>& tensors) override;
  // Throws an Error naming `what` when the ranks' tensors are not bit-identical.
  void check_identical(const std::vector<torch::Tensor>& tensors, const std::string& what) override;
  bool any(bool flag) override;
  void barrier();

 private:
  // Runs a collective, turning Gloo's failures into an Error that says which rank lost contact.
  template <typename F>
  void run(const std::string& what, F&& collective);
  DistributedOptions opt_;
  c10::intrusive_ptr<c10d::Store> store_;
  c10::intrusive_ptr<c10d::ProcessGroupGloo> pg_;
};

// A module's parameters and buffers, in a fixed order (the same on every rank).
std::vector<torch::Tensor> parameters_and_buffers(torch::nn::Module& module);

}  // namespace flatnet
