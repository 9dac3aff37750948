#pragma once
// Datasets in FlatNet's layout: a folder with measurement PNGs, ground-truth images and text lists
// (train_meas.txt, train_gt.txt, val_meas.txt, val_gt.txt), one relative path per line, same order.
// FlatNet's own lists (e.g. train_meas_ilsvrc_flatcam.txt, whose lines are relative to a data root
// such as "/root/data/") are accepted by naming the lists and the root explicitly.
#include <filesystem>
#include <string>
#include <vector>

namespace flatnet {

struct Pair {
  std::filesystem::path meas;  // raw capture (16-bit PNG)
  std::filesystem::path gt;    // ground-truth image (any size; resized to the scene size on load)
};

struct DatasetLists {
  std::filesystem::path meas_list, gt_list;
  std::filesystem::path root;  // lines are resolved against this (default: the lists' folder)
};

// Reads both lists, checks they have the same length and that every file exists (the first
// missing one is named with its list and line). Errors on an empty list.
std::vector<Pair> read_pairs(const DatasetLists& lists);

// The lists of split "train" or "val" in a dataset folder written by `flatnet simulate`.
DatasetLists split_lists(const std::filesystem::path& dataset_dir, const std::string& split);

}  // namespace flatnet
