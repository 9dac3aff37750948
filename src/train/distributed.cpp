#include "train/distributed.hpp"

#include <cstdlib>

#include <torch/csrc/distributed/c10d/ProcessGroupGloo.hpp>
#include <torch/csrc/distributed/c10d/TCPStore.hpp>

#include "core/error.hpp"
#include "core/util.hpp"

namespace flatnet {

namespace {

int env_int(const char* name, int fallback) {
  const char* v = std::getenv(name);
  if (!v || !*v) return fallback;
  try {
    size_t used = 0;
    const int x = std::stoi(v, &used);
    if (used == std::string(v).size()) return x;
  } catch (const std::exception&) {
  }
  throw Error(std::string("environment variable ") + name + "='" + v + "' is not an integer");
}

}  // namespace

DistributedOptions distributed_from_env() {
  DistributedOptions o;
  o.world_size = env_int("WORLD_SIZE", 1);
  o.rank = env_int("RANK", 0);
  if (const char* a = std::getenv("MASTER_ADDR"); a && *a) o.master_addr = a;
  o.master_port = env_int("MASTER_PORT", o.master_port);
  require(o.world_size >= 1, "WORLD_SIZE", "must be at least 1");
  require(o.rank >= 0 && o.rank < o.world_size, "RANK",
          std::to_string(o.rank) + " is outside [0, WORLD_SIZE=" + std::to_string(o.world_size) + ")");
  require(o.master_port > 0 && o.master_port < 65536, "MASTER_PORT", "must be a TCP port");
  return o;
}

ProcessGroup::ProcessGroup(const DistributedOptions& o) : opt_(o) {
  const auto timeout = std::chrono::milliseconds(static_cast<int64_t>(o.timeout_s * 1000));
  c10d::TCPStoreOptions so;
  so.port = static_cast<uint16_t>(o.master_port);
  so.isServer = o.rank == 0;
  so.numWorkers = o.world_size;
  so.waitWorkers = true;
  so.timeout = timeout;
  try {
    store_ = c10::make_intrusive<c10d::TCPStore>(o.master_addr, so);
    auto go = c10d::ProcessGroupGloo::Options::create();
    go->timeout = timeout;
    go->devices.push_back(c10d::ProcessGroupGloo::createDefaultDevice());  // the interface this host's name resolves to
    pg_ = c10::make_intrusive<c10d::ProcessGroupGloo>(store_, o.rank, o.world_size, go);
  } catch (const std::exception& e) {
    throw Error("distributed rendezvous at " + o.master_addr + ":" + std::to_string(o.master_port) + " (rank " +
                std::to_string(o.rank) + " of " + std::to_string(o.world_size) + ") failed: " +
                std::string(e.what()).substr(0, 300) + "; check MASTER_ADDR/MASTER_PORT and that every rank started");
  }
}

ProcessGroup::~ProcessGroup() = default;

template <typename F>
void ProcessGroup::run(const std::string& what, F&& collective) {
  try {
    collective();
  } catch (const std::exception& e) {
    std::string msg = e.what();
    if (const auto nl = msg.find('\n'); nl != std::string::npos) msg = msg.substr(0, nl);
    throw Error("distributed training: rank " + std::to_string(opt_.rank) + " of " + std::to_string(opt_.world_size) +
                " lost contact with the others during " + what + " (" + msg.substr(0, 300) +
                "); another rank died or stopped answering; the last checkpoint is rank 0's latest.ckpt");
  }
}

void ProcessGroup::average(const std::vector<torch::Tensor>& params) {
  if (opt_.world_size == 1) return;
  // Buckets of whole gradients, flattened into one buffer each: few, large messages.
  std::vector<torch::Tensor> bucket;
  int64_t bytes = 0;
  auto flush = [&] {
    if (bucket.empty()) return;
    std::vector<torch::Tensor> flat_parts;
    for (auto& g : bucket) flat_parts.push_back(g.reshape({-1}));
    std::vector<torch::Tensor> flat{torch::cat(flat_parts)};
    run("the gradient all-reduce", [&] { pg_->allreduce(flat)->wait(); });
    flat[0].div_(opt_.world_size);
    int64_t offset = 0;
    for (auto& g : bucket) {
      g.copy_(flat[0].slice(0, offset, offset + g.numel()).view(g.sizes()));
      offset += g.numel();
    }
    bucket.clear();
    bytes = 0;
  };
  torch::NoGradGuard no_grad;
  for (const auto& p : params) {
    if (!p.requires_grad()) continue;
    if (!p.grad().defined()) p.mutable_grad() = torch::zeros_like(p);  // unused this step: contributes 0
    bucket.push_back(p.grad());
    bytes += p.numel() * static_cast<int64_t>(p.element_size());
    if (bytes >= opt_.bucket_bytes) flush();
  }
  flush();
}

void ProcessGroup::broadcast(const std::vector<torch::Tensor>& tensors) {
  if (opt_.world_size == 1) return;
  torch::NoGradGuard no_grad;
  for (const auto& t : tensors) {
    std::vector<torch::Tensor> one{t.contiguous()};
    run("a broadcast from rank 0", [&] { pg_->broadcast(one)->wait(); });
    if (!one[0].is_same(t)) t.copy_(one[0]);
  }
}

void ProcessGroup::check_identical(const std::vector<torch::Tensor>& tensors, const std::string& what) {
  if (opt_.world_size == 1) return;
  uint64_t h = 0;
  for (const auto& t : tensors) {
    const auto c = t.detach().contiguous();
    h = stable_hash(c.data_ptr(), c.nbytes(), h);
  }
  const auto mine = torch::tensor({static_cast<int64_t>(h >> 1)}, torch::kInt64);
  std::vector<torch::Tensor> root{mine.clone()};
  run("a consistency check", [&] { pg_->broadcast(root)->wait(); });
  std::vector<torch::Tensor> differ{
      torch::tensor({root[0].item<int64_t>() != mine.item<int64_t>() ? 1 : 0}, torch::kInt64)};
  run("a consistency check", [&] { pg_->allreduce(differ)->wait(); });
  if (differ[0].item<int64_t>() > 0)
    throw Error("distributed training: " + what + " differ between ranks (" +
                std::to_string(differ[0].item<int64_t>()) + " rank(s) disagree with rank 0)");
}

bool ProcessGroup::any(bool flag) {
  if (opt_.world_size == 1) return flag;
  std::vector<torch::Tensor> t{torch::tensor({flag ? 1 : 0}, torch::kInt64)};
  run("a stop vote", [&] { pg_->allreduce(t)->wait(); });
  return t[0].item<int64_t>() > 0;
}

void ProcessGroup::barrier() {
  if (opt_.world_size == 1) return;
  run("a barrier", [&] { pg_->barrier()->wait(); });
}

std::vector<torch::Tensor> parameters_and_buffers(torch::nn::Module& module) {
  auto out = module.parameters();
  for (auto& b : module.buffers()) out.push_back(b);
  return out;
}

}  // namespace flatnet
