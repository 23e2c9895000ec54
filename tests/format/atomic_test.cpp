#include "libmodel/format/atomic.h"
#include "libmodel/format/types.h"
#include "tests/test_util.h"

#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>

using namespace orthosim;
namespace fs = std::filesystem;

TEST(Atomic, FileAppearsOnlyOnCommit) {
  test::TempDir dir("atomic");
  const std::string target = dir / "out.txt";
  test::write_file(target, "old");
  {
    AtomicFile f(target);
    std::ofstream(f.temp()) << "new";
    EXPECT_EQ(test::read_file(target), "old");
    // no commit: destructor discards
  }
  EXPECT_EQ(test::read_file(target), "old");
  EXPECT_EQ(std::distance(fs::directory_iterator(dir.path), fs::directory_iterator()), 1);
  {
    AtomicFile f(target);
    std::ofstream(f.temp()) << "new";
    f.commit();
  }
  EXPECT_EQ(test::read_file(target), "new");
}

TEST(Atomic, DirectoryMergesOnCommitAndVanishesOnFailure) {
  test::TempDir dir("atomic");
  const std::string out = dir / "out";
  {
    AtomicDir d(out);
    fs::create_directories(d.temp_path("slices"));
    std::ofstream(d.temp_path("slices/a.png")) << "a";
    EXPECT_FALSE(fs::exists(out));
  }
  EXPECT_FALSE(fs::exists(out));
  {
    AtomicDir d(out);
    fs::create_directories(d.temp_path("slices"));
    std::ofstream(d.temp_path("slices/a.png")) << "a";
    d.commit();
  }
  EXPECT_EQ(test::read_file(out + "/slices/a.png"), "a");
  {
    AtomicDir d(out);  // existing directory: merge
    std::ofstream(d.temp_path("b.txt")) << "b";
    d.commit();
  }
  EXPECT_TRUE(fs::exists(out + "/slices/a.png"));
  EXPECT_EQ(test::read_file(out + "/b.txt"), "b");
  EXPECT_EQ(std::distance(fs::directory_iterator(dir.path), fs::directory_iterator()), 1);
}

TEST(Atomic, RejectsBadTargets) {
  test::TempDir dir("atomic");
  test::write_file(dir / "file", "x");
  EXPECT_THROW(AtomicDir(dir / "file"), Error);
  EXPECT_THROW(AtomicFile(dir.path.string()), Error);
  EXPECT_THROW(AtomicFile(dir / "no/such/dir/out.h5"), Error);
  EXPECT_EQ(test::read_file(dir / "file"), "x");
}
