#pragma once
// The pickle machine behind io/torch_file (internal to the io layer): a reader of pickle protocols
// 2-5 that resolves only the globals a state dict or checkpoint needs (tensors, storages, ordered
// dicts), never runs code, and checks every size, nesting and expansion a hostile file could claim
// before it builds anything. torch_file.cpp wraps it in the zip and legacy containers.
#include <cstdint>
#include <filesystem>
#include <functional>
#include <map>
#include <memory>
#include <string>
#include <vector>

#include <torch/torch.h>

#include "core/error.hpp"
#include "io/torch_file.hpp"

namespace flatnet::pickle {

using Kind = PyValue::Kind;

PyRef make(Kind k);
PyRef make_int(int64_t i);
PyRef make_text(Kind k, std::string s);
// The storage classes torch.save names ("torch.FloatStorage", ...) and their element types.
const std::map<std::string, c10::ScalarType>& storage_types();
// Whether a pickle may name this global: the storages and the few callables a state dict needs.
bool allowed_global(const std::string& name);
// A pickled integer (or boolean), or a tuple or list of them; an Error naming `file` and `what` else.
int64_t as_int(const PyRef& v, const char* what, const std::filesystem::path& file);
std::vector<int64_t> int_tuple(const PyRef& v, const char* what, const std::filesystem::path& file);

// What a pickle may claim before flatnet refuses it: nesting (a list inside a list ... recursion
// in every walker), the expanded size of a structure that shares parts (a DAG whose walk doubles
// per level), dimensions of a tensor and elements of a storage.
constexpr int kMaxNesting = 64;
constexpr uint64_t kMaxExpandedNodes = 10'000'000;
constexpr size_t kMaxDims = 16;

// A storage named by a persistent id; its elements arrive from the container (zip record or the
// legacy file's tail), possibly after the pickle that refers to it.
struct Storage {
  c10::ScalarType dtype;
  int64_t numel = 0;
  torch::Tensor data;  // {numel} once loaded
};

// Reads one pickle (protocols 2-5) from bytes[pos..]; `persistent` resolves BINPERSID ids.
class Unpickler {
 public:
  Unpickler(const std::string& bytes, size_t pos, std::filesystem::path file,
            std::function<PyRef(const PyRef&)> persistent)
      : b_(bytes), pos_(pos), file_(std::move(file)), persistent_(std::move(persistent)) {}

  PyRef run();
  size_t position() const { return pos_; }

 private:
  const std::string& b_;
  size_t pos_;
  std::filesystem::path file_;
  std::function<PyRef(const PyRef&)> persistent_;
  std::vector<PyRef> stack_;
  std::vector<size_t> marks_;
  std::map<uint64_t, PyRef> memo_;

  [[noreturn]] void fail(const std::string& what) const {
    throw Error(file_, what + " (pickle byte " + std::to_string(pos_) + ")");
  }
  // Puts `child` into `parent`'s bookkeeping: a value once inside a container is frozen (a pickle
  // that later changes it could build a cycle, e.g. a list that contains itself), and nesting and
  // expanded size are checked against the limits before anything walks the tree.
  void adopt(PyValue& parent, const PyRef& child) {
    if (child.get() == &parent) fail("refuses a container that contains itself (hostile file?)");
    child->frozen = true;
    parent.height = std::max(parent.height, child->height + 1);
    parent.expanded = std::min(kMaxExpandedNodes + 1, parent.expanded + child->expanded);
    if (parent.height > kMaxNesting)
      fail("nests containers deeper than " + std::to_string(kMaxNesting) + " levels (hostile file?)");
    if (parent.expanded > kMaxExpandedNodes)
      fail("expands to more than " + std::to_string(kMaxExpandedNodes) + " values (shared parts; hostile file?)");
  }
  void adopt_all(PyValue& parent, const std::vector<PyRef>& children) {
    for (const auto& c : children) adopt(parent, c);
  }
  PyValue& mutable_container(const PyRef& v) {
    if (v->frozen) fail("changes a " + v->describe() + " after placing it in another value (a cycle? hostile file?)");
    return *v;
  }
  const char* take(uint64_t n) {
    if (n > b_.size() - pos_) fail("truncated: the pickle ends early (a length of " + std::to_string(n) + " bytes)");
    const char* p = b_.data() + pos_;
    pos_ += n;
    return p;
  }
  uint64_t uint_le(size_t n) {
    const auto* p = reinterpret_cast<const unsigned char*>(take(n));
    uint64_t v = 0;
    for (size_t i = 0; i < n; ++i) v |= static_cast<uint64_t>(p[i]) << (8 * i);
    return v;
  }
  std::string line() {
    const auto end = b_.find('\n', pos_);
    if (end == std::string::npos) fail("truncated: a text opcode without its newline");
    std::string s = b_.substr(pos_, end - pos_);
    pos_ = end + 1;
    return s;
  }
  PyRef pop() {
    if (stack_.empty() || (!marks_.empty() && stack_.size() <= marks_.back()))
      fail("malformed: pop from an empty stack");
    auto v = stack_.back();
    stack_.pop_back();
    return v;
  }
  PyRef& top() {
    if (stack_.empty()) fail("malformed: empty stack");
    return stack_.back();
  }
  std::vector<PyRef> pop_to_mark() {
    if (marks_.empty()) fail("malformed: no mark");
    const size_t m = marks_.back();
    marks_.pop_back();
    std::vector<PyRef> items(stack_.begin() + static_cast<std::ptrdiff_t>(m), stack_.end());
    stack_.resize(m);
    return items;
  }
  PyRef global(const std::string& module, const std::string& name) {
    const auto full = module + "." + name;
    if (objects_ && (module == "__torch__" || module.rfind("__torch__.", 0) == 0) && name == "Module")
      return make_text(Kind::global, full);  // a TorchScript module: built below as its attributes, no code run
    if (!allowed_global(full))
      fail("refuses the global '" + full +
           "': a torch.save file for flatnet may hold only tensors, storages and "
           "containers (a pickle naming other objects can run code)");
    return make_text(Kind::global, full);
  }
  PyRef tuple(std::vector<PyRef> items) {
    auto t = make(Kind::tuple);
    adopt_all(*t, items);
    t->items = std::move(items);
    return t;
  }
  PyRef list(std::vector<PyRef> items) {
    auto l = make(Kind::list);
    adopt_all(*l, items);
    l->items = std::move(items);
    return l;
  }
  void set_items(PyRef& target, const std::vector<PyRef>& kv) {
    if (target->kind != Kind::dict) fail("malformed: SETITEM(S) on a " + target->describe());
    if (kv.size() % 2) fail("malformed: SETITEMS with an odd count");
    auto& dict = mutable_container(target);
    adopt_all(dict, kv);
    for (size_t i = 0; i < kv.size(); i += 2) {
      bool replaced = false;
      if (kv[i]->kind == Kind::string || kv[i]->kind == Kind::integer)
        for (auto& e : dict.entries)
          if (e.first->kind == kv[i]->kind && e.first->text == kv[i]->text && e.first->integer == kv[i]->integer) {
            e.second = kv[i + 1];
            replaced = true;
          }
      if (!replaced) dict.entries.emplace_back(kv[i], kv[i + 1]);
    }
  }
  PyRef call(const PyRef& fn, const PyRef& args);
  PyRef rebuild_tensor(const std::vector<PyRef>& a);
  void build(const PyRef& state);
  // run()'s opcode groups: each returns false for an opcode not its own.
  bool stack_and_memo_op(unsigned char op);
  bool value_op(unsigned char op);
  bool object_op(unsigned char op);
  PyRef long_integer(size_t n);

 public:
  bool objects_ = false;  // read TorchScript modules as their attribute dicts (read_torchscript_archive)
};

}  // namespace flatnet::pickle
