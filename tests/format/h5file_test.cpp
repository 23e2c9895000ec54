#include "libmodel/format/h5file.h"
#include "tests/test_util.h"

#include <gtest/gtest.h>

using namespace orthosim;

TEST(H5File, DatasetsAndAttributesRoundTrip) {
  test::TempDir dir("h5");
  const std::string p = dir / "a.h5";
  {
    h5::File f(p, h5::File::Mode::create);
    std::vector<double> xyz = {1, 2, 3, 4, 5, 6};
    f.write<double>("/g/sub/xyz", xyz.data(), {2, 3}, "m", "two points");
    std::vector<std::uint8_t> vol(2 * 3 * 4);
    for (std::size_t i = 0; i < vol.size(); ++i) vol[i] = static_cast<std::uint8_t>(i);
    f.write<std::uint8_t>("/v", vol.data(), {2, 3, 4}, "label");
    f.write<std::int32_t>("/empty", nullptr, {0, 2}, "1");
    f.set_attr("/g", "name", "skin");
    f.set_attr("/g", "k", 2.5);
    f.set_attr("/g", "n", std::int64_t{7});
    f.set_attr("/g", "list", std::vector<double>{1, 2, 3});
    f.set_attr("/g", "names", std::vector<std::string>{"a", "bb", ""});
  }
  h5::File f(p, h5::File::Mode::read);
  std::vector<std::uint64_t> dims;
  auto xyz = f.read<double>("/g/sub/xyz", &dims);
  EXPECT_EQ(dims, (std::vector<std::uint64_t>{2, 3}));
  EXPECT_EQ(xyz, (std::vector<double>{1, 2, 3, 4, 5, 6}));
  EXPECT_EQ(f.attr_string("/g/sub/xyz", "unit"), "m");
  auto vol = f.read<std::uint8_t>("/v", &dims);
  EXPECT_EQ(dims, (std::vector<std::uint64_t>{2, 3, 4}));
  EXPECT_EQ(vol[23], 23);
  auto empty = f.read<std::int32_t>("/empty", &dims);
  EXPECT_TRUE(empty.empty());
  EXPECT_EQ(dims, (std::vector<std::uint64_t>{0, 2}));
  EXPECT_EQ(f.attr_string("/g", "name"), "skin");
  EXPECT_DOUBLE_EQ(f.attr_double("/g", "k"), 2.5);
  EXPECT_EQ(f.attr_int("/g", "n"), 7);
  EXPECT_EQ(f.attr_doubles("/g", "list"), (std::vector<double>{1, 2, 3}));
  EXPECT_EQ(f.attr_strings("/g", "names"), (std::vector<std::string>{"a", "bb", ""}));
  EXPECT_TRUE(f.exists("/g/sub"));
  EXPECT_FALSE(f.exists("/g/nope/deeper"));
  EXPECT_EQ(f.children("/g"), (std::vector<std::string>{"sub"}));
  EXPECT_EQ(f.stats().datasets_read, 3);
}

TEST(H5File, WrongTypeIsAClearError) {
  test::TempDir dir("h5");
  const std::string p = dir / "a.h5";
  {
    h5::File f(p, h5::File::Mode::create);
    std::vector<float> x = {1, 2};
    f.write<float>("/x", x.data(), {2}, "m");
  }
  h5::File f(p, h5::File::Mode::read);
  try {
    f.read<double>("/x", nullptr);
    FAIL() << "expected an error";
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("float32"), std::string::npos) << e.what();
    EXPECT_EQ(e.file(), p);
  }
}

TEST(H5File, RejectsMissingAndNonHdf5Files) {
  test::TempDir dir("h5");
  EXPECT_THROW(h5::File(dir / "missing.h5", h5::File::Mode::read), Error);
  test::write_file(dir / "text.h5", "hello, this is not HDF5\n");
  try {
    h5::File f(dir / "text.h5", h5::File::Mode::read);
    FAIL();
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("not an HDF5 file"), std::string::npos);
  }
}
