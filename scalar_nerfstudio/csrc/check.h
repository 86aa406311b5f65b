// SCALAR_CHECK(cond, parts...): TORCH_CHECK whose message is built here, without iostreams.
//
// Why: on one machine (Ubuntu 24.04, g++ 13.3, torch 2.11.0+cu130, Intel Xeon; 2026-11-26)
// a failing TORCH_CHECK whose message streamed an integer or a tensor's sizes (c10::str, an
// std::ostringstream instantiated in this extension) ended the process with a segmentation fault,
// while checks whose messages held only strings raised their RuntimeError. The same checks raise on
// Debian's g++ 12 with torch 2.15. Building the message with std::to_string (snprintf underneath)
// and handing TORCH_CHECK one C string keeps the stream code out of this extension, so a bad input
// is a Python RuntimeError everywhere, as tests/test_hash_encoding.py::test_cpp_rejects_bad_inputs
// and the other kernels' bad-input tests expect.
#pragma once

#include <ATen/core/Tensor.h>
#include <c10/core/Device.h>
#include <c10/core/ScalarType.h>
#include <c10/util/ArrayRef.h>

#include <string>
#include <type_traits>

namespace scalar_nerf {

inline void append(std::string& out, const char* text) { out += text; }
inline void append(std::string& out, const std::string& text) { out += text; }
inline void append(std::string& out, c10::ScalarType type) { out += c10::toString(type); }
inline void append(std::string& out, const c10::Device& device) { out += device.str(); }
inline void append(std::string& out, c10::IntArrayRef sizes) {
  out += '[';
  for (size_t i = 0; i < sizes.size(); ++i) {
    if (i > 0) out += ", ";
    out += std::to_string(sizes[i]);
  }
  out += ']';
}
template <typename T, typename = std::enable_if_t<std::is_arithmetic_v<T> && !std::is_same_v<T, bool>>>
void append(std::string& out, T value) {
  out += std::to_string(value);
}

// The message "part0part1..." (integers in decimal, sizes as [a, b], dtypes and devices by name).
template <typename... Parts>
std::string message(const Parts&... parts) {
  std::string out;
  (append(out, parts), ...);
  return out;
}

}  // namespace scalar_nerf

// The temporary message lives until TORCH_CHECK's error (which copies it) has been built.
#define SCALAR_CHECK(cond, ...) TORCH_CHECK((cond), ::scalar_nerf::message(__VA_ARGS__).c_str())
