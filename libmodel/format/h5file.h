// A small wrapper over the HDF5 C library: open/create files, write and read
// n-dimensional datasets of a few element types with a unit attribute, and
// attributes. Every failure throws orthosim::Error naming the file and the
// object. HDF5 types never appear in this header.
#pragma once

#include "libmodel/format/types.h"

#include <cstdint>
#include <memory>
#include <string>
#include <vector>

namespace orthosim::h5 {

enum class DType { u8, i32, i64, f32, f64 };

template <class T> constexpr DType dtype_of();
template <> constexpr DType dtype_of<std::uint8_t>() { return DType::u8; }
template <> constexpr DType dtype_of<std::int32_t>() { return DType::i32; }
template <> constexpr DType dtype_of<std::int64_t>() { return DType::i64; }
template <> constexpr DType dtype_of<float>() { return DType::f32; }
template <> constexpr DType dtype_of<double>() { return DType::f64; }
const char* dtype_name(DType t);

// What a File has read so far: lets tests prove that a loader touched only
// the groups a scene names.
struct ReadStats {
  std::int64_t datasets_read = 0;
  std::int64_t bytes_read = 0;
  std::vector<std::string> paths_read;  // every dataset read, in order
};

class File {
 public:
  enum class Mode { read, read_write, create };
  // Opens `path`. read/read_write: the file must exist and be HDF5;
  // create: truncates or creates. Throws Error(path, ...) otherwise.
  File(const std::string& path, Mode mode);
  ~File();
  File(File&&) noexcept;
  File& operator=(File&&) noexcept;
  File(const File&) = delete;
  File& operator=(const File&) = delete;

  const std::string& path() const { return path_; }
  const ReadStats& stats() const { return stats_; }

  // Objects are addressed by absolute paths like "/layers/skin/nodes".
  bool exists(const std::string& object) const;  // group or dataset
  bool is_group(const std::string& object) const;
  std::vector<std::string> children(const std::string& group) const;  // sorted
  void make_groups(const std::string& group);  // creates missing parents too
  void remove(const std::string& object);      // unlinks if present

  // Datasets. Rows of `dims` multiply to the element count. Chunked and
  // deflate-compressed when non-empty; `unit` goes into attribute "unit".
  template <class T>
  void write(const std::string& object, const T* data, const std::vector<std::uint64_t>& dims,
             const std::string& unit, const std::string& doc = "");
  // Reads a whole dataset; the stored element type must equal T.
  template <class T>
  std::vector<T> read(const std::string& object, std::vector<std::uint64_t>* dims) const;
  std::vector<std::uint64_t> dims(const std::string& object) const;
  DType dtype(const std::string& object) const;

  // Streamed datasets, for arrays too large to hold at once (segment's label
  // volume): create() makes a dataset of `dims` chunked by one row of the
  // first axis, compressed like write(); write_rows() and read_rows() move
  // rows [first, first + n) of the first axis.
  template <class T>
  void create(const std::string& object, const std::vector<std::uint64_t>& dims, const std::string& unit,
              const std::string& doc = "") {
    create_raw(object, dtype_of<T>(), dims, unit, doc);
  }
  template <class T>
  void write_rows(const std::string& object, std::uint64_t first, std::uint64_t n, const T* data) {
    rows_raw(object, dtype_of<T>(), first, n, const_cast<T*>(data), true);
  }
  template <class T>
  void read_rows(const std::string& object, std::uint64_t first, std::uint64_t n, T* out) const {
    const_cast<File*>(this)->rows_raw(object, dtype_of<T>(), first, n, out, false);
  }

  // Attributes on any object ("/" for the root).
  bool has_attr(const std::string& object, const std::string& name) const;
  void set_attr(const std::string& object, const std::string& name, const std::string& value);
  void set_attr(const std::string& object, const std::string& name, const char* value) {
    set_attr(object, name, std::string(value));
  }
  void set_attr(const std::string& object, const std::string& name, double value);
  void set_attr(const std::string& object, const std::string& name, std::int64_t value);
  void set_attr(const std::string& object, const std::string& name, const std::vector<double>& value);
  void set_attr(const std::string& object, const std::string& name,
                const std::vector<std::string>& value);
  std::string attr_string(const std::string& object, const std::string& name) const;
  double attr_double(const std::string& object, const std::string& name) const;
  std::int64_t attr_int(const std::string& object, const std::string& name) const;
  std::vector<double> attr_doubles(const std::string& object, const std::string& name) const;
  std::vector<std::string> attr_strings(const std::string& object, const std::string& name) const;

  void flush();
  void close();  // explicit close; destructor closes silently

 private:
  void read_raw(const std::string& object, DType want, void* out, std::uint64_t count) const;
  void write_raw(const std::string& object, DType type, const void* data,
                 const std::vector<std::uint64_t>& dims, const std::string& unit,
                 const std::string& doc);
  void create_raw(const std::string& object, DType type, const std::vector<std::uint64_t>& dims,
                  const std::string& unit, const std::string& doc);
  void rows_raw(const std::string& object, DType type, std::uint64_t first, std::uint64_t n, void* data,
                bool write);
  std::string path_;
  std::int64_t id_ = -1;
  mutable ReadStats stats_;
};

template <class T>
void File::write(const std::string& object, const T* data, const std::vector<std::uint64_t>& dims,
                 const std::string& unit, const std::string& doc) {
  write_raw(object, dtype_of<T>(), data, dims, unit, doc);
}

template <class T>
std::vector<T> File::read(const std::string& object, std::vector<std::uint64_t>* out_dims) const {
  std::vector<std::uint64_t> d = dims(object);
  std::uint64_t n = 1;
  for (auto x : d) n *= x;
  std::vector<T> out(n);
  read_raw(object, dtype_of<T>(), out.data(), n);
  if (out_dims) *out_dims = d;
  return out;
}

// True if `path` starts with the HDF5 signature (cheap check before opening).
bool looks_like_hdf5(const std::string& path);

}  // namespace orthosim::h5
