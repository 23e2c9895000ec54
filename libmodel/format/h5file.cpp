#include "libmodel/format/h5file.h"

#include <hdf5.h>

#include <algorithm>
#include <cstring>
#include <fstream>

namespace orthosim::h5 {
namespace {

static_assert(sizeof(hid_t) == sizeof(std::int64_t), "hid_t must be 64-bit (HDF5 >= 1.10)");

// silence HDF5's own stack printing once; errors become exceptions instead
struct Silence {
  Silence() { H5Eset_auto2(H5E_DEFAULT, nullptr, nullptr); }
};
const Silence silence_once;

hid_t native(DType t) {
  switch (t) {
    case DType::u8: return H5T_NATIVE_UINT8;
    case DType::i32: return H5T_NATIVE_INT32;
    case DType::i64: return H5T_NATIVE_INT64;
    case DType::f32: return H5T_NATIVE_FLOAT;
    case DType::f64: return H5T_NATIVE_DOUBLE;
  }
  return H5T_NATIVE_UINT8;
}

// RAII for any hid_t with its matching close function
struct Handle {
  hid_t id = -1;
  herr_t (*closer)(hid_t) = nullptr;
  Handle(hid_t i, herr_t (*c)(hid_t)) : id(i), closer(c) {}
  ~Handle() {
    if (id >= 0 && closer) closer(id);
  }
  Handle(const Handle&) = delete;
  Handle& operator=(const Handle&) = delete;
  operator hid_t() const { return id; }
};

std::string parent_of(const std::string& p) {
  auto k = p.find_last_of('/');
  if (k == std::string::npos || k == 0) return "/";
  return p.substr(0, k);
}

}  // namespace

const char* dtype_name(DType t) {
  switch (t) {
    case DType::u8: return "uint8";
    case DType::i32: return "int32";
    case DType::i64: return "int64";
    case DType::f32: return "float32";
    case DType::f64: return "float64";
  }
  return "?";
}

bool looks_like_hdf5(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) return false;
  // the superblock may sit at 0, 512, 1024, 2048 ... bytes
  const unsigned char sig[8] = {0x89, 'H', 'D', 'F', '\r', '\n', 0x1a, '\n'};
  for (std::streamoff off = 0; off <= 1 << 16; off = off == 0 ? 512 : off * 2) {
    in.clear();
    in.seekg(off);
    unsigned char buf[8];
    if (!in.read(reinterpret_cast<char*>(buf), 8)) return false;
    if (std::memcmp(buf, sig, 8) == 0) return true;
  }
  return false;
}

File::File(const std::string& path, Mode mode) : path_(path) {
  if (mode == Mode::create) {
    Handle fapl(H5Pcreate(H5P_FILE_ACCESS), H5Pclose);
    // keep files readable by HDF5 1.8-era tools and h5py alike
    H5Pset_libver_bounds(fapl, H5F_LIBVER_EARLIEST, H5F_LIBVER_LATEST);
    id_ = H5Fcreate(path.c_str(), H5F_ACC_TRUNC, H5P_DEFAULT, fapl);
    if (id_ < 0) throw Error(path, "cannot create HDF5 file");
    return;
  }
  {
    std::ifstream probe(path, std::ios::binary);
    if (!probe) throw Error(path, "cannot open file (missing or unreadable)");
  }
  if (!looks_like_hdf5(path)) throw Error(path, "not an HDF5 file");
  id_ = H5Fopen(path.c_str(), mode == Mode::read ? H5F_ACC_RDONLY : H5F_ACC_RDWR, H5P_DEFAULT);
  if (id_ < 0) throw Error(path, "cannot open HDF5 file (truncated or corrupt)");
}

File::~File() {
  if (id_ >= 0) H5Fclose(id_);
}
File::File(File&& o) noexcept : path_(std::move(o.path_)), id_(o.id_), stats_(std::move(o.stats_)) {
  o.id_ = -1;
}
File& File::operator=(File&& o) noexcept {
  if (this != &o) {
    if (id_ >= 0) H5Fclose(id_);
    path_ = std::move(o.path_);
    id_ = o.id_;
    stats_ = std::move(o.stats_);
    o.id_ = -1;
  }
  return *this;
}

void File::flush() {
  if (id_ >= 0 && H5Fflush(id_, H5F_SCOPE_GLOBAL) < 0) throw Error(path_, "cannot flush");
}

void File::close() {
  if (id_ >= 0) {
    herr_t r = H5Fclose(id_);
    id_ = -1;
    if (r < 0) throw Error(path_, "cannot close (write failed)");
  }
}

bool File::exists(const std::string& object) const {
  if (object == "/") return true;
  // walk the path: H5Lexists fails on a missing intermediate link
  std::string partial;
  std::size_t start = 1;
  while (start <= object.size()) {
    std::size_t end = object.find('/', start);
    if (end == std::string::npos) end = object.size();
    partial = object.substr(0, end);
    if (H5Lexists(id_, partial.c_str(), H5P_DEFAULT) <= 0) return false;
    if (end < object.size()) {
      H5O_info_t info;
      if (H5Oget_info_by_name2(id_, partial.c_str(), &info, H5O_INFO_BASIC, H5P_DEFAULT) < 0 ||
          info.type != H5O_TYPE_GROUP)
        return false;
    }
    start = end + 1;
  }
  return true;
}

bool File::is_group(const std::string& object) const {
  if (!exists(object)) return false;
  H5O_info_t info;
  if (H5Oget_info_by_name2(id_, object.c_str(), &info, H5O_INFO_BASIC, H5P_DEFAULT) < 0) return false;
  return info.type == H5O_TYPE_GROUP;
}

std::vector<std::string> File::children(const std::string& group) const {
  std::vector<std::string> names;
  if (!is_group(group)) return names;
  Handle g(H5Gopen2(id_, group.c_str(), H5P_DEFAULT), H5Gclose);
  if (g.id < 0) throw Error(path_, "cannot open group " + group);
  auto cb = [](hid_t, const char* name, const H5L_info_t*, void* data) -> herr_t {
    static_cast<std::vector<std::string>*>(data)->push_back(name);
    return 0;
  };
  H5Literate(g, H5_INDEX_NAME, H5_ITER_INC, nullptr, cb, &names);
  std::sort(names.begin(), names.end());
  return names;
}

void File::make_groups(const std::string& group) {
  if (group == "/" || exists(group)) return;
  make_groups(parent_of(group));
  // no object times: the same content makes the same bytes (HDF5 stamps
  // each object's creation time by default)
  Handle gcpl(H5Pcreate(H5P_GROUP_CREATE), H5Pclose);
  H5Pset_obj_track_times(gcpl, 0);
  Handle g(H5Gcreate2(id_, group.c_str(), H5P_DEFAULT, gcpl, H5P_DEFAULT), H5Gclose);
  if (g.id < 0) throw Error(path_, "cannot create group " + group);
}

void File::remove(const std::string& object) {
  if (!exists(object)) return;
  if (H5Ldelete(id_, object.c_str(), H5P_DEFAULT) < 0) throw Error(path_, "cannot remove " + object);
}

void File::write_raw(const std::string& object, DType type, const void* data,
                     const std::vector<std::uint64_t>& dims, const std::string& unit,
                     const std::string& doc) {
  make_groups(parent_of(object));
  remove(object);
  std::vector<hsize_t> hd(dims.begin(), dims.end());
  std::uint64_t n = 1;
  for (auto d : dims) n *= d;
  Handle space(H5Screate_simple(static_cast<int>(hd.size()), hd.data(), nullptr), H5Sclose);
  if (space.id < 0) throw Error(path_, "cannot create dataspace for " + object);
  Handle dcpl(H5Pcreate(H5P_DATASET_CREATE), H5Pclose);
  H5Pset_obj_track_times(dcpl, 0);  // (as make_groups)
  if (n > 0 && !hd.empty()) {
    // chunks of ~64k elements along the first axis, whole rows
    std::vector<hsize_t> chunk = hd;
    hsize_t row = 1;
    for (std::size_t i = 1; i < hd.size(); ++i) row *= hd[i];
    chunk[0] = std::max<hsize_t>(1, std::min<hsize_t>(hd[0], (1u << 16) / std::max<hsize_t>(row, 1)));
    H5Pset_chunk(dcpl, static_cast<int>(chunk.size()), chunk.data());
    H5Pset_shuffle(dcpl);
    H5Pset_deflate(dcpl, 1);
  }
  Handle ds(H5Dcreate2(id_, object.c_str(), native(type), space, H5P_DEFAULT, dcpl, H5P_DEFAULT),
            H5Dclose);
  if (ds.id < 0) throw Error(path_, "cannot create dataset " + object);
  if (n > 0 && H5Dwrite(ds, native(type), H5S_ALL, H5S_ALL, H5P_DEFAULT, data) < 0)
    throw Error(path_, "cannot write dataset " + object);
  set_attr(object, "unit", unit);
  if (!doc.empty()) set_attr(object, "doc", doc);
}

void File::create_raw(const std::string& object, DType type, const std::vector<std::uint64_t>& dims,
                      const std::string& unit, const std::string& doc) {
  make_groups(parent_of(object));
  remove(object);
  std::vector<hsize_t> hd(dims.begin(), dims.end());
  std::uint64_t n = 1;
  for (auto d : dims) n *= d;
  if (hd.empty() || n == 0) throw Error(path_, "cannot create an empty streamed dataset " + object);
  Handle space(H5Screate_simple(static_cast<int>(hd.size()), hd.data(), nullptr), H5Sclose);
  if (space.id < 0) throw Error(path_, "cannot create dataspace for " + object);
  Handle dcpl(H5Pcreate(H5P_DATASET_CREATE), H5Pclose);
  H5Pset_obj_track_times(dcpl, 0);  // (as make_groups)
  std::vector<hsize_t> chunk = hd;
  chunk[0] = 1;
  H5Pset_chunk(dcpl, static_cast<int>(chunk.size()), chunk.data());
  H5Pset_shuffle(dcpl);
  H5Pset_deflate(dcpl, 1);
  Handle ds(H5Dcreate2(id_, object.c_str(), native(type), space, H5P_DEFAULT, dcpl, H5P_DEFAULT),
            H5Dclose);
  if (ds.id < 0) throw Error(path_, "cannot create dataset " + object);
  set_attr(object, "unit", unit);
  if (!doc.empty()) set_attr(object, "doc", doc);
}

void File::rows_raw(const std::string& object, DType type, std::uint64_t first, std::uint64_t n, void* data,
                    bool write) {
  if (!write && dtype(object) != type)
    throw Error(path_, object + " has element type " + dtype_name(dtype(object)) + ", expected " +
                           dtype_name(type));
  std::vector<hsize_t> hd;
  for (auto d : dims(object)) hd.push_back(d);
  if (hd.empty() || first + n > hd[0]) throw Error(path_, "rows out of range in " + object);
  if (n == 0) return;
  Handle ds(H5Dopen2(id_, object.c_str(), H5P_DEFAULT), H5Dclose);
  Handle fspace(H5Dget_space(ds), H5Sclose);
  std::vector<hsize_t> start(hd.size(), 0), count = hd;
  start[0] = first;
  count[0] = n;
  H5Sselect_hyperslab(fspace, H5S_SELECT_SET, start.data(), nullptr, count.data(), nullptr);
  Handle mspace(H5Screate_simple(static_cast<int>(count.size()), count.data(), nullptr), H5Sclose);
  herr_t rc = write ? H5Dwrite(ds, native(type), mspace, fspace, H5P_DEFAULT, data)
                    : H5Dread(ds, native(type), mspace, fspace, H5P_DEFAULT, data);
  if (rc < 0)
    throw Error(path_, std::string(write ? "cannot write rows of " : "cannot read rows of (corrupt or truncated) ") +
                           object);
  if (!write) {
    std::uint64_t elems = 1;
    for (auto c : count) elems *= c;
    stats_.datasets_read += 1;
    stats_.bytes_read += static_cast<std::int64_t>(elems * H5Tget_size(native(type)));
    stats_.paths_read.push_back(object);
  }
}

std::vector<std::uint64_t> File::dims(const std::string& object) const {
  if (!exists(object)) throw Error(path_, "missing dataset " + object);
  Handle ds(H5Dopen2(id_, object.c_str(), H5P_DEFAULT), H5Dclose);
  if (ds.id < 0) throw Error(path_, object + " is not a dataset");
  Handle space(H5Dget_space(ds), H5Sclose);
  int rank = H5Sget_simple_extent_ndims(space);
  if (rank < 0) throw Error(path_, "cannot read the shape of " + object);
  std::vector<hsize_t> hd(static_cast<std::size_t>(rank));
  H5Sget_simple_extent_dims(space, hd.data(), nullptr);
  return {hd.begin(), hd.end()};
}

DType File::dtype(const std::string& object) const {
  if (!exists(object)) throw Error(path_, "missing dataset " + object);
  Handle ds(H5Dopen2(id_, object.c_str(), H5P_DEFAULT), H5Dclose);
  if (ds.id < 0) throw Error(path_, object + " is not a dataset");
  Handle t(H5Dget_type(ds), H5Tclose);
  H5T_class_t c = H5Tget_class(t);
  std::size_t size = H5Tget_size(t);
  if (c == H5T_FLOAT) {
    if (size == 4) return DType::f32;
    if (size == 8) return DType::f64;
  } else if (c == H5T_INTEGER) {
    bool is_signed = H5Tget_sign(t) == H5T_SGN_2;
    if (size == 1 && !is_signed) return DType::u8;
    if (size == 4 && is_signed) return DType::i32;
    if (size == 8 && is_signed) return DType::i64;
  }
  throw Error(path_, object + " has an unsupported element type");
}

void File::read_raw(const std::string& object, DType want, void* out, std::uint64_t count) const {
  DType have = dtype(object);
  if (have != want)
    throw Error(path_, object + " has element type " + dtype_name(have) + ", expected " +
                           dtype_name(want));
  Handle ds(H5Dopen2(id_, object.c_str(), H5P_DEFAULT), H5Dclose);
  if (count > 0 && H5Dread(ds, native(want), H5S_ALL, H5S_ALL, H5P_DEFAULT, out) < 0)
    throw Error(path_, "cannot read dataset " + object + " (corrupt or truncated)");
  std::size_t elem = H5Tget_size(native(want));
  stats_.datasets_read += 1;
  stats_.bytes_read += static_cast<std::int64_t>(count * elem);
  stats_.paths_read.push_back(object);
}

// ---- attributes ------------------------------------------------------------

namespace {

struct AttrTarget {
  Handle obj;
  explicit AttrTarget(hid_t file, const std::string& path, const std::string& fname)
      : obj(H5Oopen(file, path.c_str(), H5P_DEFAULT), H5Oclose) {
    if (obj.id < 0) throw Error(fname, "cannot open object " + path);
  }
};

void replace_attr(hid_t obj, const std::string& name) {
  if (H5Aexists(obj, name.c_str()) > 0) H5Adelete(obj, name.c_str());
}

}  // namespace

bool File::has_attr(const std::string& object, const std::string& name) const {
  if (!exists(object)) return false;
  AttrTarget t(id_, object, path_);
  return H5Aexists(t.obj, name.c_str()) > 0;
}

void File::set_attr(const std::string& object, const std::string& name, const std::string& value) {
  AttrTarget t(id_, object, path_);
  replace_attr(t.obj, name);
  Handle type(H5Tcopy(H5T_C_S1), H5Tclose);
  H5Tset_size(type, H5T_VARIABLE);
  H5Tset_cset(type, H5T_CSET_UTF8);
  Handle space(H5Screate(H5S_SCALAR), H5Sclose);
  Handle a(H5Acreate2(t.obj, name.c_str(), type, space, H5P_DEFAULT, H5P_DEFAULT), H5Aclose);
  const char* p = value.c_str();
  if (a.id < 0 || H5Awrite(a, type, &p) < 0) throw Error(path_, "cannot write attribute " + name);
}

void File::set_attr(const std::string& object, const std::string& name,
                    const std::vector<std::string>& value) {
  AttrTarget t(id_, object, path_);
  replace_attr(t.obj, name);
  Handle type(H5Tcopy(H5T_C_S1), H5Tclose);
  H5Tset_size(type, H5T_VARIABLE);
  H5Tset_cset(type, H5T_CSET_UTF8);
  hsize_t n = value.size();
  Handle space(H5Screate_simple(1, &n, nullptr), H5Sclose);
  std::vector<const char*> ptrs;
  for (auto& s : value) ptrs.push_back(s.c_str());
  Handle a(H5Acreate2(t.obj, name.c_str(), type, space, H5P_DEFAULT, H5P_DEFAULT), H5Aclose);
  if (a.id < 0 || (n > 0 && H5Awrite(a, type, ptrs.data()) < 0))
    throw Error(path_, "cannot write attribute " + name);
}

void File::set_attr(const std::string& object, const std::string& name, double value) {
  AttrTarget t(id_, object, path_);
  replace_attr(t.obj, name);
  Handle space(H5Screate(H5S_SCALAR), H5Sclose);
  Handle a(H5Acreate2(t.obj, name.c_str(), H5T_IEEE_F64LE, space, H5P_DEFAULT, H5P_DEFAULT), H5Aclose);
  if (a.id < 0 || H5Awrite(a, H5T_NATIVE_DOUBLE, &value) < 0)
    throw Error(path_, "cannot write attribute " + name);
}

void File::set_attr(const std::string& object, const std::string& name, std::int64_t value) {
  AttrTarget t(id_, object, path_);
  replace_attr(t.obj, name);
  Handle space(H5Screate(H5S_SCALAR), H5Sclose);
  Handle a(H5Acreate2(t.obj, name.c_str(), H5T_STD_I64LE, space, H5P_DEFAULT, H5P_DEFAULT), H5Aclose);
  if (a.id < 0 || H5Awrite(a, H5T_NATIVE_INT64, &value) < 0)
    throw Error(path_, "cannot write attribute " + name);
}

void File::set_attr(const std::string& object, const std::string& name, const std::vector<double>& value) {
  AttrTarget t(id_, object, path_);
  replace_attr(t.obj, name);
  hsize_t n = value.size();
  Handle space(H5Screate_simple(1, &n, nullptr), H5Sclose);
  Handle a(H5Acreate2(t.obj, name.c_str(), H5T_IEEE_F64LE, space, H5P_DEFAULT, H5P_DEFAULT), H5Aclose);
  if (a.id < 0 || (n > 0 && H5Awrite(a, H5T_NATIVE_DOUBLE, value.data()) < 0))
    throw Error(path_, "cannot write attribute " + name);
}

namespace {

struct OpenAttr {
  Handle a;
  Handle type;
  Handle space;
  std::size_t count = 0;
  OpenAttr(hid_t file, const std::string& object, const std::string& name, const std::string& fname)
      : a(-1, H5Aclose), type(-1, H5Tclose), space(-1, H5Sclose) {
    Handle obj(H5Oopen(file, object.c_str(), H5P_DEFAULT), H5Oclose);
    if (obj.id < 0) throw Error(fname, "missing object " + object);
    if (H5Aexists(obj, name.c_str()) <= 0)
      throw Error(fname, "missing attribute '" + name + "' on " + object);
    a.id = H5Aopen(obj, name.c_str(), H5P_DEFAULT);
    type.id = H5Aget_type(a);
    space.id = H5Aget_space(a);
    hssize_t n = H5Sget_simple_extent_npoints(space);
    count = n < 0 ? 0 : static_cast<std::size_t>(n);
  }
};

}  // namespace

std::vector<std::string> File::attr_strings(const std::string& object, const std::string& name) const {
  OpenAttr at(id_, object, name, path_);
  if (H5Tget_class(at.type) != H5T_STRING)
    throw Error(path_, "attribute '" + name + "' on " + object + " is not a string");
  std::vector<std::string> out;
  if (H5Tis_variable_str(at.type) > 0) {
    std::vector<char*> ptrs(at.count, nullptr);
    Handle mem(H5Tcopy(H5T_C_S1), H5Tclose);
    H5Tset_size(mem, H5T_VARIABLE);
    H5Tset_cset(mem, H5Tget_cset(at.type));
    if (at.count && H5Aread(at.a, mem, ptrs.data()) < 0)
      throw Error(path_, "cannot read attribute " + name);
    for (char* p : ptrs) out.emplace_back(p ? p : "");
    if (at.count) H5Dvlen_reclaim(mem, at.space, H5P_DEFAULT, ptrs.data());
  } else {
    std::size_t len = H5Tget_size(at.type);
    std::vector<char> buf(len * at.count + 1, 0);
    if (at.count && H5Aread(at.a, at.type, buf.data()) < 0)
      throw Error(path_, "cannot read attribute " + name);
    for (std::size_t i = 0; i < at.count; ++i) {
      std::string s(buf.data() + i * len, len);
      s.erase(std::find(s.begin(), s.end(), '\0'), s.end());
      out.push_back(s);
    }
  }
  return out;
}

std::string File::attr_string(const std::string& object, const std::string& name) const {
  auto v = attr_strings(object, name);
  if (v.size() != 1) throw Error(path_, "attribute '" + name + "' on " + object + " is not a single string");
  return v[0];
}

std::vector<double> File::attr_doubles(const std::string& object, const std::string& name) const {
  OpenAttr at(id_, object, name, path_);
  H5T_class_t c = H5Tget_class(at.type);
  if (c != H5T_FLOAT && c != H5T_INTEGER)
    throw Error(path_, "attribute '" + name + "' on " + object + " is not numeric");
  std::vector<double> out(at.count);
  if (at.count && H5Aread(at.a, H5T_NATIVE_DOUBLE, out.data()) < 0)
    throw Error(path_, "cannot read attribute " + name);
  return out;
}

double File::attr_double(const std::string& object, const std::string& name) const {
  auto v = attr_doubles(object, name);
  if (v.size() != 1) throw Error(path_, "attribute '" + name + "' on " + object + " is not a scalar");
  return v[0];
}

std::int64_t File::attr_int(const std::string& object, const std::string& name) const {
  OpenAttr at(id_, object, name, path_);
  if (H5Tget_class(at.type) != H5T_INTEGER || at.count != 1)
    throw Error(path_, "attribute '" + name + "' on " + object + " is not an integer");
  std::int64_t v = 0;
  if (H5Aread(at.a, H5T_NATIVE_INT64, &v) < 0) throw Error(path_, "cannot read attribute " + name);
  return v;
}

}  // namespace orthosim::h5
