// The translation unit the shared precompiled header (core/pch.hpp) is built from.
