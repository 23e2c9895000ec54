// Plain data types shared by every stage and the runtime.
//
// Arrays follow the model file: one row per item, row-major, so an (n x 3)
// array is n consecutive xyz triples, exactly as HDF5 stores it.
#pragma once

#include <Eigen/Core>

#include <cstdint>
#include <stdexcept>
#include <string>
#include <type_traits>

namespace orthosim {

// (rows x W) row-major array; W == 1 is a plain column vector.
template <class T, int W>
using Rows = std::conditional_t<W == 1, Eigen::Matrix<T, Eigen::Dynamic, 1>,
                                Eigen::Matrix<T, Eigen::Dynamic, W, Eigen::RowMajor>>;

using MatX2d = Rows<double, 2>;
using MatX3d = Rows<double, 3>;
using MatX2i = Rows<std::int32_t, 2>;
using MatX3i = Rows<std::int32_t, 3>;
using MatX4i = Rows<std::int32_t, 4>;
using VecXd = Rows<double, 1>;
using VecXi = Rows<std::int32_t, 1>;
using VecXu8 = Rows<std::uint8_t, 1>;

// The error every offline stage throws. `file` names the input or output the
// problem is about (may be empty); what() is "<file>: <message>" so the CLI
// can print it as one line.
class Error : public std::runtime_error {
 public:
  Error(std::string file, const std::string& message)
      : std::runtime_error(file.empty() ? message : file + ": " + message),
        file_(std::move(file)),
        message_(message) {}
  const std::string& file() const { return file_; }
  const std::string& message() const { return message_; }

 private:
  std::string file_;
  std::string message_;
};

}  // namespace orthosim
