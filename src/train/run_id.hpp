#pragma once
// A training run's identity. Every run folder records its run's id (OUT/run_id.txt) and every
// checkpoint the run writes carries it: a latest.ckpt of another run, copied into the folder, would
// otherwise resume that run's weights under this folder's logs, best model and settings. Used by all
// three trainers (GAN, mask, code pair).
#include <filesystem>
#include <string>

namespace flatnet {

// A new run's id: 16 hex digits from the system's entropy source.
std::string new_run_id();

// Whether `id` has the form new_run_id gives (16 lowercase hex digits).
bool is_run_id(const std::string& id);

// The id recorded in OUT/run_id.txt; "" when the folder has none (a new folder, or a run from before
// run ids).
std::string folder_run_id(const std::filesystem::path& out);

// Writes OUT/run_id.txt atomically.
void record_run_id(const std::filesystem::path& out, const std::string& id);

// The id a mask or code-pair run goes on under, recorded in OUT/run_id.txt: when resuming, the
// checkpoint's `resumed_id` (refused when the folder records another run, unless `force`; a new id
// for a checkpoint from before run ids), else a new one.
std::string settle_run_id(const std::filesystem::path& out, bool resuming, const std::string& resumed_id,
                          const std::filesystem::path& checkpoint, bool force);

// Refuses `checkpoint` (whose run id is `checkpoint_id`, "" for files from before run ids) when the
// folder `out` records another run, naming both ids and `force_key`, the setting that resumes it
// anyway. A folder without a record accepts any checkpoint.
void require_checkpoint_of_this_run(const std::filesystem::path& out, const std::string& checkpoint_id,
                                    const std::filesystem::path& checkpoint, const std::string& force_key);

}  // namespace flatnet
