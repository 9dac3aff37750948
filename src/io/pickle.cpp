#include "io/pickle.hpp"

#include <algorithm>
#include <cstring>

#include "core/util.hpp"

namespace flatnet::pickle {

PyRef make(Kind k) {
  auto v = std::make_shared<PyValue>();
  v->kind = k;
  return v;
}
PyRef make_int(int64_t i) {
  auto v = make(Kind::integer);
  v->integer = i;
  return v;
}
PyRef make_text(Kind k, std::string s) {
  auto v = make(k);
  v->text = std::move(s);
  return v;
}

// The globals a state dict or checkpoint needs; nothing else is ever resolved.
const std::map<std::string, c10::ScalarType>& storage_types() {
  static const std::map<std::string, c10::ScalarType> t = {
      {"torch.FloatStorage", torch::kFloat32}, {"torch.DoubleStorage", torch::kFloat64},
      {"torch.HalfStorage", torch::kFloat16},  {"torch.BFloat16Storage", torch::kBFloat16},
      {"torch.LongStorage", torch::kInt64},    {"torch.IntStorage", torch::kInt32},
      {"torch.ShortStorage", torch::kInt16},   {"torch.CharStorage", torch::kInt8},
      {"torch.ByteStorage", torch::kUInt8},    {"torch.BoolStorage", torch::kBool}};
  return t;
}
bool allowed_global(const std::string& name) {
  static const std::vector<std::string> callables = {
      "collections.OrderedDict",
      "torch._utils._rebuild_tensor_v2",
      "torch._utils._rebuild_tensor",
      "torch._utils._rebuild_parameter",
      "torch.Size",
      "torch.jit._pickle.restore_type_tag"};  // LibTorch's pickle_save (flatnet's exports before 2026-11)
  return storage_types().count(name) || std::find(callables.begin(), callables.end(), name) != callables.end();
}

int64_t as_int(const PyRef& v, const char* what, const std::filesystem::path& file) {
  if (!v || (v->kind != Kind::integer && v->kind != Kind::boolean))
    throw Error(file, std::string("malformed tensor: ") + what + " is not an integer");
  return v->kind == Kind::boolean ? v->boolean : v->integer;
}

std::vector<int64_t> int_tuple(const PyRef& v, const char* what, const std::filesystem::path& file) {
  if (!v || (v->kind != Kind::tuple && v->kind != Kind::list))
    throw Error(file, std::string("malformed tensor: ") + what + " is not a tuple");
  std::vector<int64_t> out;
  for (const auto& i : v->items) out.push_back(as_int(i, what, file));
  return out;
}

// _rebuild_tensor_v2(storage, storage_offset, size, stride, requires_grad, backward_hooks[, metadata])
// and the older _rebuild_tensor(storage, storage_offset, size, stride): a strided view of the
// storage, copied out. Floating types become float32 (flatnet's weights are float32).
PyRef Unpickler::rebuild_tensor(const std::vector<PyRef>& a) {
  if (a.size() < 4 || a[0]->kind != Kind::storage)
    fail("malformed tensor: expected (storage, offset, size, stride, ...)");
  const auto offset = as_int(a[1], "storage offset", file_);
  const auto size = int_tuple(a[2], "size", file_), stride = int_tuple(a[3], "stride", file_);
  if (size.size() != stride.size()) fail("malformed tensor: size and stride differ in length");
  if (size.size() > kMaxDims) fail("malformed tensor: " + std::to_string(size.size()) + " dimensions");
  auto v = make(Kind::tensor);
  v->integer = offset;
  std::vector<PyRef> sizes, strides;
  for (auto s : size) sizes.push_back(make_int(s));
  for (auto s : stride) strides.push_back(make_int(s));
  // The storage; the view is taken once the storage's elements are loaded.
  std::vector<PyRef> parts = {a[0], tuple(sizes), tuple(strides)};
  adopt_all(*v, parts);
  v->items = parts;
  return v;
}

PyRef Unpickler::call(const PyRef& fn, const PyRef& args) {
  if (fn->kind != Kind::global) fail("refuses to call a " + fn->describe() + " (only allow-listed globals are called)");
  if (args->kind != Kind::tuple) fail("malformed: REDUCE arguments are not a tuple");
  const auto& a = args->items;
  if (fn->text == "collections.OrderedDict") {
    auto d = make(Kind::dict);
    if (!a.empty() && (a[0]->kind == Kind::list || a[0]->kind == Kind::tuple))
      for (const auto& kv : a[0]->items)
        if (kv->kind == Kind::tuple && kv->items.size() == 2) {
          adopt_all(*d, kv->items);
          d->entries.emplace_back(kv->items[0], kv->items[1]);
        }
    return d;
  }
  if (fn->text == "torch._utils._rebuild_tensor_v2" || fn->text == "torch._utils._rebuild_tensor")
    return rebuild_tensor(a);
  if (fn->text == "torch._utils._rebuild_parameter") {  // (data, requires_grad, backward_hooks)
    if (a.empty() || a[0]->kind != Kind::tensor) fail("malformed parameter: its data is not a tensor");
    return a[0];
  }
  if (fn->text == "torch.Size") return a.empty() ? tuple({}) : tuple(a[0]->items);
  if (fn->text == "torch.jit._pickle.restore_type_tag") {  // (value, type string): the value
    if (a.empty()) fail("malformed restore_type_tag call");
    return a[0];
  }
  fail("refuses to call '" + fn->text + "'");
}

// BUILD: a TorchScript module (objects_) takes its state dict's entries as attributes; an
// OrderedDict's or tensor's attributes (state_dict's _metadata) are not needed.
void Unpickler::build(const PyRef& state) {
  auto& target = top();
  if (target->kind == Kind::dict && target->text.rfind("object ", 0) == 0) {
    if (state->kind != Kind::dict) fail("malformed: a module's state is a " + state->describe() + ", not a dict");
    auto& obj = mutable_container(target);
    adopt(obj, state);
    obj.entries.insert(obj.entries.end(), state->entries.begin(), state->entries.end());
    return;
  }
  if (target->kind != Kind::dict && target->kind != Kind::tensor) fail("refuses BUILD on a " + target->describe());
}

// Pickle opcodes (Python's Lib/pickletools.py names them; protocols 0-5, those torch.save writes).
enum PickleOp : unsigned char {
  kProto = 0x80,
  kFrame = 0x95,
  kStop = '.',
  kMark = '(',
  kPop = '0',
  kPopMark = '1',
  kDup = '2',
  kEmptyDict = '}',
  kEmptyList = ']',
  kEmptyTuple = ')',
  kEmptySet = 0x8f,
  kTuple = 't',
  kTuple1 = 0x85,
  kTuple2 = 0x86,
  kTuple3 = 0x87,
  kList = 'l',
  kDict = 'd',
  kFrozenset = 0x91,
  kBinput = 'q',
  kLongBinput = 'r',
  kMemoize = 0x94,
  kBinget = 'h',
  kLongBinget = 'j',
  kBinint = 'J',
  kBinint1 = 'K',
  kBinint2 = 'M',
  kLong1 = 0x8a,
  kLong4 = 0x8b,
  kBinfloat = 'G',
  kNone = 'N',
  kNewTrue = 0x88,
  kNewFalse = 0x89,
  kBinunicode = 'X',
  kShortBinunicode = 0x8c,
  kBinunicode8 = 0x8d,
  kShortBinstring = 'U',
  kBinstring = 'T',
  kShortBinbytes = 'C',
  kBinbytes = 'B',
  kBinbytes8 = 0x8e,
  kGlobal = 'c',
  kStackGlobal = 0x93,
  kReduce = 'R',
  kNewobj = 0x81,
  kNewobjEx = 0x92,
  kBuild = 'b',
  kSetitem = 's',
  kSetitems = 'u',
  kAppend = 'a',
  kAppends = 'e',
  kAdditems = 0x90,
  kBinpersid = 'Q',
};

PyRef Unpickler::run() {
  while (true) {
    const auto op = static_cast<unsigned char>(*take(1));
    if (op == kStop) {
      if (stack_.size() != 1 || !marks_.empty())
        fail("malformed: STOP with " + std::to_string(stack_.size()) + " values");
      return stack_.back();
    }
    if (stack_and_memo_op(op) || value_op(op) || object_op(op)) continue;
    std::ostringstream os;
    os << "unknown pickle opcode 0x" << std::hex << static_cast<int>(op);
    --pos_;
    fail(os.str());
  }
}

// Framing, marks, containers built from the stack, the memo, POP and DUP.
bool Unpickler::stack_and_memo_op(unsigned char op) {
  switch (op) {
    case kProto:
      take(1);
      return true;
    case kFrame:
      take(8);
      return true;  // the frame's bytes follow inline
    case kMark:
      marks_.push_back(stack_.size());
      return true;
    case kPop:
      pop();
      return true;
    case kPopMark:
      pop_to_mark();
      return true;
    case kDup:
      stack_.push_back(top());
      return true;
    case kEmptyDict:
      stack_.push_back(make(Kind::dict));
      return true;
    case kEmptyList:
      stack_.push_back(make(Kind::list));
      return true;
    case kEmptyTuple:
      stack_.push_back(tuple({}));
      return true;
    case kEmptySet:
      stack_.push_back(make(Kind::list));
      return true;  // a set is kept as a list
    case kTuple:
      stack_.push_back(tuple(pop_to_mark()));
      return true;
    case kTuple1: {
      auto a = pop();
      stack_.push_back(tuple({a}));
      return true;
    }
    case kTuple2: {
      auto b = pop(), a = pop();
      stack_.push_back(tuple({a, b}));
      return true;
    }
    case kTuple3: {
      auto c = pop(), b = pop(), a = pop();
      stack_.push_back(tuple({a, b, c}));
      return true;
    }
    case kList:
      stack_.push_back(list(pop_to_mark()));
      return true;
    case kFrozenset:
      stack_.push_back(list(pop_to_mark()));
      return true;
    case kDict: {
      auto d = make(Kind::dict);
      set_items(d, pop_to_mark());
      stack_.push_back(d);
      return true;
    }
    case kBinput:
      memo_[uint_le(1)] = top();
      return true;
    case kLongBinput:
      memo_[uint_le(4)] = top();
      return true;
    case kMemoize:
      memo_[memo_.size()] = top();
      return true;
    case kBinget:
    case kLongBinget: {
      const auto k = uint_le(op == kBinget ? 1 : 4);
      const auto it = memo_.find(k);
      if (it == memo_.end()) fail("malformed: memo " + std::to_string(k) + " was never stored");
      stack_.push_back(it->second);
      return true;
    }
    default:
      return false;
  }
}

// LONG1/LONG4's n bytes: little-endian two's complement. Only the legacy format's magic number is
// longer than 8 bytes; it is kept as big-endian hex text.
PyRef Unpickler::long_integer(size_t n) {
  if (n > 8) {
    const auto* p = reinterpret_cast<const unsigned char*>(take(n));
    std::ostringstream hex;
    hex << std::hex;
    bool leading = true;
    for (size_t i = n; i-- > 0;) {
      if (leading && p[i] == 0) continue;
      hex << (leading ? "" : (p[i] < 16 ? "0" : "")) << static_cast<int>(p[i]);
      leading = false;
    }
    return make_text(Kind::integer, hex.str());
  }
  uint64_t v = n ? uint_le(n) : 0;
  if (n && n < 8 && (v >> (8 * n - 1)) & 1) v |= ~uint64_t(0) << (8 * n);
  return make_int(static_cast<int64_t>(v));
}

// Scalars: integers, floats, None, booleans, strings and bytes.
bool Unpickler::value_op(unsigned char op) {
  const auto text = [&](Kind kind, uint64_t length_bytes) {
    const auto n = uint_le(length_bytes);
    stack_.push_back(make_text(kind, std::string(take(n), n)));
    return true;
  };
  switch (op) {
    case kBinint:
      stack_.push_back(make_int(static_cast<int32_t>(uint_le(4))));
      return true;
    case kBinint1:
      stack_.push_back(make_int(static_cast<int64_t>(uint_le(1))));
      return true;
    case kBinint2:
      stack_.push_back(make_int(static_cast<int64_t>(uint_le(2))));
      return true;
    case kLong1:
    case kLong4:
      stack_.push_back(long_integer(uint_le(op == kLong1 ? 1 : 4)));
      return true;
    case kBinfloat: {  // big-endian IEEE double
      const auto* p = reinterpret_cast<const unsigned char*>(take(8));
      uint64_t bits = 0;
      for (int i = 0; i < 8; ++i) bits = (bits << 8) | p[i];
      auto v = make(Kind::real);
      std::memcpy(&v->real, &bits, 8);
      stack_.push_back(v);
      return true;
    }
    case kNone:
      stack_.push_back(make(Kind::none));
      return true;
    case kNewTrue:
    case kNewFalse: {
      auto v = make(Kind::boolean);
      v->boolean = op == kNewTrue;
      stack_.push_back(v);
      return true;
    }
    case kShortBinunicode:
      return text(Kind::string, 1);
    case kBinunicode:
      return text(Kind::string, 4);
    case kBinunicode8:
      return text(Kind::string, 8);
    case kShortBinstring:
      return text(Kind::string, 1);
    case kBinstring:
      return text(Kind::string, 4);
    case kShortBinbytes:
      return text(Kind::bytes, 1);
    case kBinbytes:
      return text(Kind::bytes, 4);
    case kBinbytes8:
      return text(Kind::bytes, 8);
    default:
      return false;
  }
}

// Globals, calls and object building: where a pickle could run code, so each is allow-listed
// (global, call) or refused.
bool Unpickler::object_op(unsigned char op) {
  switch (op) {
    case kGlobal: {  // "module\nname\n"
      const auto module = line();
      stack_.push_back(global(module, line()));
      return true;
    }
    case kStackGlobal: {
      auto name = pop(), module = pop();
      if (name->kind != Kind::string || module->kind != Kind::string) fail("malformed: STACK_GLOBAL without strings");
      stack_.push_back(global(module->text, name->text));
      return true;
    }
    case kReduce: {
      auto args = pop(), fn = pop();
      stack_.push_back(call(fn, args));
      return true;
    }
    case kNewobj: {  // only a TorchScript module, as the dict of its attributes
      auto args = pop(), cls = pop();
      if (!objects_ || cls->kind != Kind::global) fail("refuses NEWOBJ: the file constructs a class instance");
      auto obj = make(Kind::dict);
      obj->text = "object " + cls->text;
      stack_.push_back(obj);
      return true;
    }
    case kNewobjEx:
      fail("refuses NEWOBJ_EX: the file constructs a class instance");
    case kBuild:
      build(pop());
      return true;
    case kSetitem: {
      auto v = pop(), k = pop();
      set_items(top(), {k, v});
      return true;
    }
    case kSetitems:
      set_items(top(), pop_to_mark());
      return true;
    case kAppend: {
      auto v = pop();
      if (top()->kind != Kind::list) fail("malformed: APPEND to a " + top()->describe());
      auto& l = mutable_container(top());
      adopt(l, v);
      l.items.push_back(v);
      return true;
    }
    case kAppends:
    case kAdditems: {
      auto items = pop_to_mark();
      if (top()->kind != Kind::list) fail("malformed: APPENDS to a " + top()->describe());
      auto& l = mutable_container(top());
      adopt_all(l, items);
      l.items.insert(l.items.end(), items.begin(), items.end());
      return true;
    }
    case kBinpersid: {
      auto pid = pop();
      stack_.push_back(persistent_(pid));
      return true;
    }
    default:
      return false;
  }
}

}  // namespace flatnet::pickle
