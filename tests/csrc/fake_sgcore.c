/* Fake SGCore C subset for the senseglove plugin tests: one Nova glove (FAKE_SG_DEVICES=0: none),
 * fixed wrist position [mm] and flexions, records every SGCore_SendHaptics call.
 * FAKE_SG_REPORT=<file>: SGCore_Dispose writes the counts there (runs in another process).
 * FAKE_SG_FAIL_AFTER=<n>: the glove stops answering after n position reads (disconnect). */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

static int g_init, g_sends, g_stops, g_disposed;
static int g_last_ffb[8], g_last_n, g_last_vibro;
static int g_history[4096][4];

static int n_devices(void) { const char *e = getenv("FAKE_SG_DEVICES"); return e ? atoi(e) : 1; }

int SGCore_Init(void) { g_init++; return 1; }
int SGCore_DeviceCount(void) { return n_devices(); }
int SGCore_IsNova(int glove) { return glove < n_devices(); }
int SGCore_GetFlexions(int glove, float *out, int n) {
    if (glove >= n_devices()) return 0;
    for (int k = 0; k < n; k++) out[k] = 0.1f * (float)(k + 1);
    return 1;
}
static int g_reads;
int SGCore_GetWristPosition(int glove, float *out) {
    const char *fail = getenv("FAKE_SG_FAIL_AFTER");
    if (glove >= n_devices() || (fail && ++g_reads > atoi(fail))) return 0;
    out[0] = 10.0f; out[1] = 20.0f; out[2] = 30.0f;   /* mm */
    return 1;
}
int SGCore_SendHaptics(int glove, const int *ffb, int n, int vibro) {
    if (glove >= n_devices() || n > 8) return 0;
    for (int k = 0; k < n; k++) { g_last_ffb[k] = ffb[k]; if (k < 4 && g_sends < 4096) g_history[g_sends][k] = ffb[k]; }
    g_last_n = n; g_last_vibro = vibro; g_sends++;
    return 1;
}
int SGCore_StopHaptics(int glove) { (void)glove; g_stops++; memset(g_last_ffb, 0, sizeof g_last_ffb); return 1; }
void SGCore_Dispose(void) {
    g_disposed++;
    const char *path = getenv("FAKE_SG_REPORT");
    if (path) {
        FILE *f = fopen(path, "w");
        if (f) {
            fprintf(f, "sends %d\nstops %d\nlast %d %d %d %d\n", g_sends, g_stops,
                    g_last_ffb[0], g_last_ffb[1], g_last_ffb[2], g_last_ffb[3]);
            fclose(f);
        }
    }
}

/* ---- test queries ---- */
int fake_sg_sends(void) { return g_sends; }
int fake_sg_stops(void) { return g_stops; }
int fake_sg_disposed(void) { return g_disposed; }
int fake_sg_last_level(int k) { return g_last_ffb[k]; }
int fake_sg_last_n(void) { return g_last_n; }
int fake_sg_history(int i, int k) { return g_history[i][k]; }
